"""Outputs and numbers through one gate: every output is a regular file outside any model folder, an export
keeps what its model promises, every number is checked as it is parsed, series steps agree on their grid,
integers are exact in float32, and the Python API raises ``ApmgsrnError`` for every bad argument.

Every hostile input is built here: named pipes with ``os.mkfifo``, a brick model copied from tests/data, series
steps edited from the real viscous-fingering crops. ``/dev/null`` is only ever passed to the checks that refuse
before writing (``check_output_target``/``check_output_path``), never to a command that could write there.
"""

from __future__ import annotations

import ast
import hashlib
import os
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest

import apmgsrn
from apmgsrn import export as export_module
from apmgsrn.atomic import atomic_write_text, check_output_path, check_output_target
from apmgsrn.cli.main import main
from apmgsrn.data import ArrayVolume, open_volume
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.options import TrainOptions
from apmgsrn.series.data import open_series
from apmgsrn.training.trainer import TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")

REPO = Path(__file__).resolve().parents[1]
FAST = ["--grids", "2", "--resolution", "4", "--iterations", "3", "--batch-size", "512", "--device", "cpu"]
STEPS = ("030_density_030_064_2.0.vti", "031_density_031_064_2.0.vti")


def one_line_error(capsys, *needles: str) -> str:
    """The error: one line ``error: ...`` last on stderr, no traceback; every needle in it."""
    err = capsys.readouterr().err
    last = err.rstrip("\n").splitlines()[-1]
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert last.startswith("error: ") and len(errors) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in last, err
    return last


def digest(path: Path) -> str:
    """SHA-256 of every file under a folder (names included), or of one file."""
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        h.update(str(file.relative_to(path) if path.is_dir() else "").encode())
        h.update(file.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def model(tmp_path_factory, test_data) -> Path:
    """A float32 model trained here on the real neghip 24^3 crop of tests/data."""
    folder = tmp_path_factory.mktemp("gates")
    out = folder / "m.apmgsrn"
    assert main(["train", str(test_data / "reference_neghip_24.npy"), "--out", str(out), *FAST]) == 0
    return out


@pytest.fixture()
def bricks(tmp_path, test_data) -> Path:
    """A copy of the reference brick model (a manifest and two bricks)."""
    folder = tmp_path / "bricks"
    shutil.copytree(test_data / "reference_bricks", folder)
    return folder


# ----------------------------------------------------------------------------- outputs: not a regular file
def test_a_character_device_is_refused_before_anything_is_written():
    for check in (check_output_target, check_output_path):
        with pytest.raises(ApmgsrnError, match="is a character device, not a regular file"):
            check(os.devnull, "plot")
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)


def test_a_pipe_or_a_link_to_one_is_never_replaced(tmp_path):
    pipe = tmp_path / "pipe.png"
    os.mkfifo(pipe)
    (tmp_path / "link.png").symlink_to(pipe)
    for target in (pipe, tmp_path / "link.png"):
        with pytest.raises(ApmgsrnError, match="is a named pipe"):
            atomic_write_text(target, "text", "plot")
    assert stat.S_ISFIFO(os.lstat(pipe).st_mode) and (tmp_path / "link.png").is_symlink()


@pytest.mark.parametrize("command", ["decode", "render", "info --plot", "export"])
def test_commands_refuse_a_named_pipe_as_output(command, model, tmp_path, capsys):
    suffix = {"decode": ".npy", "render": ".png", "info --plot": ".png", "export": ".onnx"}[command]
    pipe = tmp_path / f"out{suffix}"
    os.mkfifo(pipe)
    argv = {"decode": ["decode", str(model), "--out", str(pipe)],
            "render": ["render", str(model), "--out", str(pipe), "--width", "8", "--height", "8"],
            "info --plot": ["info", str(model), "--plot", str(pipe)],
            "export": ["export", str(model), "--out", str(pipe)]}[command]
    assert main(argv) == 2
    one_line_error(capsys, str(pipe), "named pipe")
    assert stat.S_ISFIFO(os.lstat(pipe).st_mode) and sorted(tmp_path.iterdir()) == [pipe]


@pytest.mark.parametrize("argv, flag", [
    (["info", "{m}", "--plot", "{tmp}/curves"], "--plot"),
    (["info", "{m}", "--plot", "{tmp}/curves.txt"], "--plot"),
    (["export", "{m}", "--out", "{tmp}/graph"], "--out"),
    (["export", "{m}", "--out", "{tmp}/graph.png"], "--out"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_outputs_whose_suffix_names_their_format_need_it(argv, flag, model, tmp_path, capsys):
    assert main([a.format(m=model, tmp=tmp_path) for a in argv]) == 2
    one_line_error(capsys, "must be named", flag)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- outputs: not part of a model
@pytest.mark.parametrize("case", ["info --plot manifest", "info --plot beside", "export into", "decode into",
                                  "render into", "pack onto a brick", "train onto a brick"])
def test_no_command_writes_into_a_brick_model(case, model, bricks, test_data, capsys):
    before = digest(bricks)
    data = test_data / "reference_neghip_24.npy"
    argv = {
        "info --plot manifest": ["info", str(model), "--plot", str(bricks / "manifest.json")],
        "info --plot beside": ["info", str(model), "--plot", str(bricks / "curves.png")],
        "export into": ["export", str(model), "--out", str(bricks / "graph.onnx")],
        "decode into": ["decode", str(model), "--out", str(bricks / "decoded.npy")],
        "render into": ["render", str(model), "--out", str(bricks / "r.png"), "--width", "8", "--height", "8"],
        "pack onto a brick": ["pack", str(bricks / "brick_000_000_000.apmgsrn"), str(data), "--out",
                              str(bricks / "brick_001_000_000.apmgsrn"), "--bits", "8"],
        "train onto a brick": ["train", str(data), "--out", str(bricks / "brick_000_000_000.apmgsrn"), *FAST],
    }[case]
    assert main(argv) == 2
    one_line_error(capsys, "model folder", str(bricks))
    assert digest(bricks) == before


def test_the_python_api_writes_into_no_brick_model_either(model, bricks, tmp_path):
    before = digest(bricks)
    loaded = apmgsrn.load(model)
    for write in (lambda: loaded.save(bricks / "brick_000_000_000.apmgsrn"),
                  lambda: loaded.export_onnx(bricks / "graph.onnx"),
                  lambda: loaded.save_decoded(bricks / "decoded.npy")):
        with pytest.raises(ApmgsrnError, match="lies in the model folder"):
            write()
    pipe = tmp_path / "pipe.apmgsrn"
    os.mkfifo(pipe)
    with pytest.raises(ApmgsrnError, match="named pipe"):
        loaded.save(pipe)
    assert digest(bricks) == before and stat.S_ISFIFO(os.lstat(pipe).st_mode)


def test_brick_training_still_writes_and_finishes_its_own_folder(test_data, tmp_path, capsys):
    out = tmp_path / "bricks"
    argv = ["train", str(test_data / "reference_neghip_24.npy"), "--out", str(out), "--bricks", "2,1,1",
            "--workers", "1", "--model", "apmgsrn", *FAST]
    assert main(argv) == 0
    assert main(argv) == 0  # the same run again: its manifest is rewritten, the bricks reused
    assert apmgsrn.load(out).description.bricks is not None


# ----------------------------------------------------------------------------- export keeps the promise
def test_export_refuses_a_model_whose_bound_needs_its_correction(model, test_data, tmp_path, capsys):
    packed = tmp_path / "bounded.apmgsrn"
    assert main(["pack", str(model), str(test_data / "reference_neghip_24.npy"), "--out", str(packed),
                 "--max-error", "0.5"]) == 0
    assert apmgsrn.load(packed).field.correction_count > 0
    capsys.readouterr()
    assert main(["export", str(packed), "--out", str(tmp_path / "bounded.onnx")]) == 2
    one_line_error(capsys, str(packed), "correction", "--max-error")
    assert not (tmp_path / "bounded.onnx").exists()


def test_export_of_a_brick_model_beyond_its_brick_limit_is_one_line(bricks, tmp_path, monkeypatch, capsys):
    from dataclasses import replace

    monkeypatch.setattr(export_module, "LIMITS", replace(export_module.LIMITS, export_bricks=1))
    assert main(["export", str(bricks), "--out", str(tmp_path / "b.onnx")]) == 2
    one_line_error(capsys, "2 bricks", "at most 1")
    assert not (tmp_path / "b.onnx").exists()


# ----------------------------------------------------------------------------- numbers
NUMBER_PROBES = [
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--iterations", "9223372036854775808"], "--iterations"),
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--iterations", "9223372036854775807"], "--iterations"),
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--seed", "18446744073709551616"], "--seed"),
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--grids", "9223372036854775808"], "--grids"),
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--fill-nonfinite", "1e39"], "--fill-nonfinite"),
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--log-offset", "1e400"], "--log-offset"),
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--max-error", "nan"], "--max-error"),
    (["train", "{v}", "--out", "{tmp}/m.apmgsrn", "--voxel-fraction", "1.5"], "--voxel-fraction"),
    (["pack", "{m}", "{v}", "--out", "{tmp}/p.apmgsrn", "--psnr-loss", "1e30"], "--psnr-loss"),
    (["pack", "{m}", "{v}", "--out", "{tmp}/p.apmgsrn", "--ratio", "inf"], "--ratio"),
    (["pack", "{m}", "{v}", "--out", "{tmp}/p.apmgsrn", "--size", "9223372036854775808"], "--size"),
    (["decode", "{m}", "--out", "{tmp}/d.npy", "--batch-size", "9223372036854775808"], "--batch-size"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--azimuth", "1e400"], "--azimuth"),
    (["render", "{m}", "--out", "{tmp}/r.gif", "--frames", "9223372036854775807"], "--frames"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--seed", "-9223372036854775809"], "--seed"),
    (["grids", "{m}", "{v}", "--out", "{tmp}/g", "--animate", "--iterations", "9223372036854775807"],
     "--iterations"),
    (["eval", "{m}", "{v}", "--batch-size", "1e3"], "--batch-size"),
]


@pytest.mark.parametrize("probe, flag", NUMBER_PROBES, ids=[" ".join(p[:1] + p[-2:]) for p, _ in NUMBER_PROBES])
def test_every_number_is_bounded_as_it_is_parsed(probe, flag, model, test_data, tmp_path, capsys):
    argv = [a.format(m=model, v=test_data / "reference_neghip_24.npy", tmp=tmp_path) for a in probe]
    assert main(argv) == 2
    one_line_error(capsys, flag)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("options", [{"iterations": 2**63}, {"iterations": 10**12}, {"psnr_loss": 1e30},
                                     {"lr": float("inf")}, {"seed": -1}, {"fill_nonfinite": 1e39}],
                         ids=lambda o: next(iter(o)))
def test_python_callers_meet_the_same_ranges(options, test_data):
    name = next(iter(options))
    with pytest.raises(InvalidArgument, match=f"^{name}="):
        TrainOptions.from_kwargs(**options)
    with pytest.raises(InvalidArgument, match=f"^{name}="):
        apmgsrn.plan(test_data / "reference_neghip_24.npy", **options)


def test_training_configs_bound_iterations_for_every_caller():
    with pytest.raises(InvalidArgument, match="^iterations="):
        TrainConfig(iterations=2**63)


# ----------------------------------------------------------------------------- series steps
@pytest.fixture()
def steps(tmp_path, test_data) -> Path:
    """Two real steps of the viscous-fingering run, copied."""
    folder = tmp_path / "steps"
    folder.mkdir()
    for name in STEPS:
        shutil.copy(test_data / "viscous_fingers_run01" / name, folder / name)
    return folder


@pytest.mark.parametrize("change", [(b'Spacing="1 1 1"', b'Spacing="1 2 1"'),
                                    (b'Origin="16 16 32"', b'Origin="16 16 33"')], ids=["spacing", "origin"])
def test_series_steps_must_lie_on_one_grid(change, steps, tmp_path, capsys):
    second = steps / STEPS[1]
    text = second.read_bytes()
    assert change[0] in text
    second.write_bytes(text.replace(change[0], change[1], 1))
    with pytest.raises(ApmgsrnError, match="same grid"):
        open_series(str(steps / "*.vti")).volume(1)
    out = tmp_path / "series.apmgsrn"
    assert main(["train", str(steps / "*.vti"), "--out", str(out), *FAST]) == 2
    one_line_error(capsys, STEPS[1], "origin, spacing")
    assert not out.exists()


@pytest.mark.parametrize("timestep", ["nan", "inf", "-inf"])
def test_a_pvd_with_a_timestep_that_is_no_finite_number_is_refused(timestep, steps, model, tmp_path, capsys):
    pvd = steps / "run.pvd"
    pvd.write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1"><Collection>\n'
                   f'<DataSet timestep="0" file="{STEPS[0]}"/>\n<DataSet timestep="{timestep}" file="{STEPS[1]}"/>\n'
                   '</Collection></VTKFile>\n')
    out = tmp_path / "good.apmgsrn"
    shutil.copy(model, out)  # a good model already under --out
    before = out.read_bytes()
    assert main(["train", str(pvd), "--out", str(out), *FAST]) == 2
    one_line_error(capsys, STEPS[1], "not a finite number")
    assert out.read_bytes() == before


# ----------------------------------------------------------------------------- integers exact in float32
def test_int64_data_that_float32_would_round_is_refused(tmp_path, capsys):
    data = (np.int64(2**62) + np.arange(6 * 7 * 8, dtype=np.int64)).reshape(6, 7, 8)
    with pytest.raises(ApmgsrnError, match="cannot hold exactly"):
        ArrayVolume(data).stats()
    path = tmp_path / "large.npy"
    np.save(path, data)
    assert main(["train", str(path), "--out", str(tmp_path / "m.apmgsrn"), *FAST]) == 2
    one_line_error(capsys, str(path), "int64", "cannot hold exactly")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["large.npy"]


def test_integers_float32_holds_exactly_still_read():
    small = np.arange(6 * 7 * 8, dtype=np.int64).reshape(6, 7, 8) - 100
    assert np.array_equal(ArrayVolume(small).read(), small.astype(np.float32))
    powers = np.full((2, 2, 2), 2**40, dtype=np.int64)  # large, but a power of two: exact
    assert ArrayVolume(powers).stats().max == 2.0**40


# ----------------------------------------------------------------------------- the public API
@pytest.mark.parametrize("call", [
    "decode shape huge", "decode shape int", "decode shape float", "decode shape text", "render model",
    "render value_range", "render value_range nan", "render opacity", "render colormap", "render preset_units",
    "load path", "predict text", "export path",
])
def test_the_api_raises_apmgsrn_error_for_every_bad_argument(call, model):
    loaded = apmgsrn.load(model)
    calls = {
        "decode shape huge": lambda: loaded.decode(shape=(10**6, 10**6, 10**6)),
        "decode shape int": lambda: loaded.decode(shape=5),
        "decode shape float": lambda: loaded.decode(shape=(2.5, 2, 2)),
        "decode shape text": lambda: loaded.decode(shape="abc"),
        "render model": lambda: apmgsrn.render("model.apmgsrn"),
        "render value_range": lambda: apmgsrn.render(loaded, value_range=5),
        "render value_range nan": lambda: apmgsrn.render(loaded, value_range=(float("nan"), 1.0)),
        "render opacity": lambda: apmgsrn.render(loaded, opacity=[(0.5,)], width=8, height=8),
        "render colormap": lambda: apmgsrn.render(loaded, colormap=5, width=8, height=8),
        "render preset_units": lambda: apmgsrn.render(loaded, preset_units="x", width=8, height=8),
        "load path": lambda: apmgsrn.load(5),
        "predict text": lambda: loaded.predict("abc"),
        "export path": lambda: loaded.export_onnx(None),
    }
    with pytest.raises(ApmgsrnError):
        calls[call]()


def test_decode_sizes_are_checked_before_allocating(model):
    with pytest.raises(ApmgsrnError, match="memory budget|from 1 to"):
        apmgsrn.load(model).decode(shape=(1 << 20, 1 << 20, 1 << 20))


# ----------------------------------------------------------------------------- the ParaView plugin
def _plugin_model_path():
    """``model_path`` of the plugin, taken from its source (the module itself imports ParaView)."""
    source = (REPO / "src" / "apmgsrn" / "paraview_plugin" / "apmgsrn_reader.py").read_text()
    tree = ast.parse(source)
    wanted = [node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name == "model_path"]
    namespace = {"os": os, "MANIFEST_NAME": "manifest.json"}
    exec(compile(ast.Module(body=wanted, type_ignores=[]), "apmgsrn_reader.py", "exec"), namespace)
    return namespace["model_path"]


def test_the_plugin_never_passes_a_model_name_as_an_option(model, tmp_path, monkeypatch, capsys):
    model_path = _plugin_model_path()
    monkeypatch.chdir(tmp_path)
    shutil.copy(model, tmp_path / "-h")
    path = model_path("-h")
    assert not path.startswith("-") and Path(path) == tmp_path / "-h"
    assert model_path(str(tmp_path / "bricks" / "manifest.json")) == str(tmp_path / "bricks")
    out = tmp_path / "decoded.vti"
    assert main(["decode", path, "--out", str(out), "--json"]) == 0  # the arguments the plugin builds
    assert open_volume(out).shape == apmgsrn.load(model).description.volume_shape


# ----------------------------------------------------------------------------- found by a fresh probe round
def test_predict_refuses_ragged_and_oversized_points_and_takes_a_series_step(model, tmp_path, test_data):
    loaded = apmgsrn.load(model)
    with pytest.raises(ApmgsrnError, match="points"):
        loaded.predict([[0.0, 0.0, 0.0], [1.0, 2.0]])
    huge = np.lib.stride_tricks.as_strided(np.zeros(3, np.float32), shape=(10**10, 3), strides=(0, 4))
    with pytest.raises(ApmgsrnError, match="memory budget"):
        loaded.predict(huge)
    series = tmp_path / "s.apmgsrn"
    assert main(["train", str(test_data / "viscous_fingers_run01" / "03[01]_*.vti"), "--out", str(series),
                 *FAST]) == 0
    two = apmgsrn.load(series)
    points = np.zeros((2, 3), np.float32)
    assert np.isfinite(two.predict(points, time=1)).all()
    with pytest.raises(ApmgsrnError):
        two.predict(points, time=5)


def test_a_brick_model_answers_nan_points_with_nan(tmp_path, test_data):
    folder = tmp_path / "b"
    assert main(["train", str(test_data / "reference_neghip_24.npy"), "--bricks", "2,1,1", "--out", str(folder),
                 "--workers", "1", *FAST]) == 0
    points = np.array([[np.nan, 0, 0], [0, 0, 0], [np.inf, -np.inf, 0], [1e30, 0, 0]], np.float32)
    values = apmgsrn.load(folder).predict(points)
    assert np.isnan(values[0]) and np.isfinite(values[1:]).all()
    manifest = folder / "manifest.json"
    text = manifest.read_text()
    import json

    from apmgsrn.io.container import sealed_manifest_text

    record = json.loads(text)
    record["run_id"] = "0" * 32  # the bricks were trained by another run than the folder names
    manifest.write_text(sealed_manifest_text(record))
    with pytest.raises(ApmgsrnError, match="run"):
        apmgsrn.load(folder)


def test_the_api_refuses_a_value_outside_an_options_choices():
    with pytest.raises(ApmgsrnError, match="transform='sqrt'"):
        apmgsrn.plan(np.zeros((8, 8, 8), np.float32), transform="sqrt")
