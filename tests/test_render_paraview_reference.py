"""Colour maps against ParaView itself: every preset ParaView ships, and presets of our own in its lenient
JSON and legacy XML formats, applied by ParaView's ``pvpython`` and by us, compared value by value.

One ``pvpython`` run (``tests/paraview_scripts/dump_colors.py``) applies every preset two ways (stretched
over a range, as ParaView applies presets, and kept in the preset's own units) and writes ParaView's
colours and opacities at chosen values; the tests read the same presets from ParaView's own printout and
compare. Marker ``paraview``: skipped without ``pvpython`` (Debian's ``paraview`` package).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.colormaps import builtin_colormap
from apmgsrn.rendering.paraview import apply_preset, load_transfer_function, read_presets

pytestmark = pytest.mark.paraview

SCRIPTS = Path(__file__).parent / "paraview_scripts"
EXTRA_JSON = SCRIPTS / "extra_presets.json"  # comments, trailing commas, opacity, log scale, ...
LEGACY_XML = SCRIPTS / "legacy_presets.xml"
RANGE = (-3.7, 12.5)  # any range; not [0, 1], so every preset is moved
# The ends, just inside them (where a clamped lookup and an interpolated one could part), an even grid
# and random values.
FRACTIONS = np.concatenate(
    [
        [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 1 - 1e-3, 1 - 1e-6, 1 - 1e-9, 1 - 1e-12, 1.0],
        np.linspace(0.0, 1.0, 161)[1:-1],
        np.random.default_rng(0).random(60),
    ]
)
TOLERANCE = 1.0 / 255.0  # one step of an 8-bit colour: what the renderer's table must meet
# The colour maps themselves do ParaView's arithmetic, so they agree far closer (measured: 2e-14); a
# tight bound catches any drift that one 8-bit step would hide.
SAME = 1e-9


@pytest.fixture(scope="module")
def paraview(tmp_path_factory) -> dict:
    """ParaView's colours for every preset, and our reading of the presets ParaView printed."""
    folder = tmp_path_factory.mktemp("paraview")
    request = {
        "imports": [str(EXTRA_JSON), str(LEGACY_XML)],
        "range": list(RANGE),
        "fractions": FRACTIONS.tolist(),
        "presets_out": str(folder / "presets.json"),
    }
    (folder / "request.json").write_text(json.dumps(request))
    # A private HOME: importing presets makes ParaView save them to its user settings.
    env = {**os.environ, "HOME": str(folder), "XDG_CONFIG_HOME": str(folder / "config")}
    script = SCRIPTS / "dump_colors.py"
    command = [shutil.which("pvpython"), str(script), str(folder / "request.json"), str(folder / "out.json")]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    result = json.loads((folder / "out.json").read_text())
    result["presets_file"] = folder / "presets.json"
    return result


def _continuous(paraview: dict) -> list[tuple[dict, object]]:
    """ParaView's entries with colour nodes, each beside our reading of the same preset (file order)."""
    ours = read_presets(paraview["presets_file"])
    theirs = [entry for entry in paraview["presets"] if "normalized" in entry]
    assert [p.name for p in ours] == [e["name"] for e in theirs]
    return list(zip(theirs, ours))


def _tied_positions_reordered(entry: dict, preset) -> list[float]:
    """Positions (stretched over RANGE) where ParaView ended up with tied nodes in another order.

    ParaView sorts the nodes with C++'s std::sort, which may reorder nodes that share a position; with
    GCC's library it does so for one built-in preset ("Muted Blue-Green": four nodes at 0.5, 27 in all).
    We keep the file's order. Both orders hold the same nodes; they differ only just above the tie.
    """
    theirs = np.asarray(entry["normalized"]["rgb_points"]).reshape(-1, 4)
    ours = np.asarray(apply_preset(preset, RANGE).color_map.points)
    np.testing.assert_allclose(theirs[:, 0], ours[:, 0], rtol=0, atol=1e-12)
    reordered = []
    for x in np.unique(ours[:, 0]):
        here = np.isclose(ours[:, 0], x, rtol=0, atol=1e-12)
        if not np.array_equal(theirs[here, 1:], ours[here, 1:]):
            # Same colours, other order.
            assert sorted(map(tuple, theirs[here, 1:])) == sorted(map(tuple, ours[here, 1:]))
            reordered.append(float(x))
    return reordered


def test_paraview_presets_load_as_paraview_prints_them(paraview):
    # All of ParaView's presets (195 in 5.11) as ParaView prints them, plus the imported ones: every entry
    # with colour nodes is read, every categorical one (IndexedColors and no nodes) is left out.
    names = [p.name for p in read_presets(paraview["presets_file"])]
    entries = paraview["presets"]
    assert paraview["builtin_count"] >= 195
    assert names == [e["name"] for e in entries if "normalized" in e]
    assert len(names) >= 128  # 5.11's continuous built-ins


def test_our_lenient_json_and_xml_files_hold_what_paraview_imports(paraview):
    # ParaView's reader takes the comments and trailing commas of EXTRA_JSON, and converts LEGACY_XML; we
    # find the same presets in both files (continuous and categorical alike).
    imported = paraview["imported"]
    assert imported[str(EXTRA_JSON)] == 13 and imported[str(LEGACY_XML)] == 6
    builtin = paraview["builtin_count"]
    imported_entries = paraview["presets"][builtin:]
    ours = [p.name for p in read_presets(EXTRA_JSON)] + [p.name for p in read_presets(LEGACY_XML)]
    assert ours == [e["name"] for e in imported_entries if "normalized" in e]
    categorical = {e["name"] for e in imported_entries if e["categorical"]}
    assert categorical == {"apmgsrn categorical", "apmgsrn indexed with nodes", "xml categorical"}


def test_every_continuous_preset_matches_paraview_over_a_rescaled_range(paraview):
    failures = []
    for entry, preset in _continuous(paraview):
        values = np.asarray(entry["normalized"]["values"])
        theirs = np.asarray(entry["normalized"]["rgb"])
        ours = apply_preset(preset, RANGE).color_map.evaluate(values)
        compared = np.ones(len(values), dtype=bool)
        reordered = _tied_positions_reordered(entry, preset)
        if reordered:
            # With ParaView's order of the tied nodes our lookup gives ParaView's colours everywhere ...
            nodes = np.asarray(entry["normalized"]["rgb_points"]).reshape(-1, 4)
            same_nodes = replace(preset.color_map, points=tuple(map(tuple, nodes)))
            np.testing.assert_allclose(same_nodes.evaluate(values), theirs, rtol=0, atol=SAME)
            # ... and with the file's order everywhere but the segment just above the tie.
            xs = nodes[:, 0]
            for x in reordered:
                above = xs[xs > x + 1e-12][0]
                compared &= ~((values > x) & (values <= above))
        error = np.abs(ours - theirs).max(axis=1)[compared]
        if error.max() > SAME:
            worst = np.argmax(error)
            failures.append(f"{entry['name']!r}: {error.max():.2g} at {values[compared][worst]:.6g}")
    assert not failures, "colours differ from ParaView's: " + "; ".join(failures)


def test_every_continuous_preset_in_its_own_units_matches_paraview(paraview):
    # ParaView's "use preset range" (ApplyPreset(name, rescale=False)): nodes stay where they are, and
    # UseLogScale given as a number turns the lookup table's log scale on.
    failures = []
    for entry, preset in _continuous(paraview):
        values = np.asarray(entry["data"]["values"])
        tf = apply_preset(preset, None, units="data")
        assert tf.color_map.log_scale == entry["data"]["log_scale"], entry["name"]
        error = np.abs(tf.color_map.evaluate(values) - np.asarray(entry["data"]["rgb"])).max()
        if error > SAME:
            failures.append(f"{entry['name']!r}: {error:.2g}")
    assert not failures, "colours differ from ParaView's: " + "; ".join(failures)
    assert any(entry["data"]["log_scale"] for entry, _ in _continuous(paraview))  # the log case was there


def test_opacity_points_match_paraview_both_ways(paraview):
    checked = 0
    for entry, preset in _continuous(paraview):
        if "opacity" not in entry["normalized"]:
            continue
        for units, range_ in (("normalized", RANGE), ("data", None)):
            values = np.asarray(entry[units]["values"])
            ours = apply_preset(preset, range_, units=units).opacity_map.evaluate(values)
            np.testing.assert_allclose(ours, entry[units]["opacity"], rtol=0, atol=SAME, err_msg=entry["name"])
        checked += 1
    assert checked == 3  # the presets of EXTRA_JSON with Points (midpoints, sharpness, log scale)


def test_the_renderer_table_matches_paraview_away_from_jumps(paraview):
    # The renderer looks colours up in a 4096-entry table interpolated linearly, as VTK's volume mappers
    # do. It agrees with ParaView except next to (1.5 entries) a node where the colour jumps (Step maps,
    # nodes sharing a position) or bends sharply: a node of a segment whose colour changes by more than
    # an 8-bit step per table entry, where the table cuts the corner.
    failures = []
    for entry, preset in _continuous(paraview):
        tf = apply_preset(preset, RANGE)
        values = np.asarray(entry["normalized"]["values"])
        colours, _ = tf.table(4096).lookup(torch.tensor(values, dtype=torch.float32))
        nodes = np.asarray(tf.color_map.points)  # [P, 4]
        xs = nodes[:, 0]
        entry_width = (RANGE[1] - RANGE[0]) / 4095
        change = np.abs(np.diff(nodes[:, 1:], axis=0)).max(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):  # nodes sharing a position
            steep = np.flatnonzero(change * entry_width / np.diff(xs) > TOLERANCE)
        sharp = xs if tf.color_map.color_space == "Step" else np.concatenate([xs[steep], xs[steep + 1]])
        far = np.ones(len(values), dtype=bool)
        for x in sharp:
            far &= np.abs(values - x) > 1.5 * entry_width
        for x in _tied_positions_reordered(entry, preset):
            far &= ~((values > x) & (values <= xs[xs > x + 1e-12][0]))
        error = np.abs(colours.double().numpy() - np.asarray(entry["normalized"]["rgb"])).max(axis=1)[far]
        if error.max() > TOLERANCE:
            failures.append(f"{entry['name']!r}: {error.max():.4f}")
    assert not failures, "table colours differ from ParaView's: " + "; ".join(failures)


def test_categorical_presets_are_what_paraview_applies_as_categories(paraview):
    # ParaView switches the lookup table to categories for every preset with IndexedColors. Those with no
    # colour nodes are exactly the ones we leave out, and asking for one by name says why. One with nodes
    # as well ("apmgsrn indexed with nodes") is read for its nodes, which ParaView's volume lookup uses
    # (compared with the others above).
    for entry in paraview["presets"]:
        if "normalized" not in entry:
            assert entry["categorical"], entry["name"]
    both = [e["name"] for e in paraview["presets"] if e["categorical"] and "normalized" in e]
    assert both == ["apmgsrn indexed with nodes"]
    with pytest.raises(ApmgsrnError, match="categorical"):
        load_transfer_function(paraview["presets_file"], RANGE, name="KAAMS")  # the first KAAMS is indexed


@pytest.mark.parametrize(
    "ours, theirs",
    [("Cool to Warm", "Cool to Warm"), ("grayscale", "Grayscale"), ("viridis", "Viridis (matplotlib)"),
     ("plasma", "Plasma (matplotlib)"), ("inferno", "Inferno (matplotlib)"), ("magma", "Magma (matplotlib)"),
     ("turbo", "Turbo")],
)
def test_built_in_maps_match_paraviews_presets_of_the_same_name(paraview, ours, theirs):
    entry = next(e for e in paraview["presets"] if e["name"] == theirs)
    values = np.asarray(entry["normalized"]["values"])
    colours = builtin_colormap(ours).rescaled(*RANGE).evaluate(values)
    np.testing.assert_allclose(colours, entry["normalized"]["rgb"], rtol=0, atol=TOLERANCE)
