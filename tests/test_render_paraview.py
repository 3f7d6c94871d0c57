"""ParaView colour-map presets: JSON (ParaView's lenient form) and legacy XML, presets and session exports,
ParaView's rules for applying them, errors, and writing them back. The comparison with ParaView itself is
in test_render_paraview_reference.py (needs pvpython)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.color_spaces import rgb_to_lab
from apmgsrn.rendering.colormaps import make_transfer_function
from apmgsrn.rendering.paraview import load_transfer_function, read_presets, save_transfer_function

# A preset file as ParaView's preset dialog exports it: tab-indented list, nodes on [0, 1].
PRESET_FILE = """[
\t{
\t\t"ColorSpace" : "Lab",
\t\t"Creator" : "Someone",
\t\t"Name" : "Blue to Gold",
\t\t"NanColor" : [ 0.25, 0.0, 0.0 ],
\t\t"RGBPoints" : [ 0.0, 0.0, 0.0, 0.5, 0.5, 1.0, 1.0, 1.0, 1.0, 0.9, 0.6, 0.0 ]
\t},
\t{
\t\t"ColorSpace" : "RGB",
\t\t"Name" : "Black, White",
\t\t"NanColor" : [ 1, 0, 0 ],
\t\t"RGBPoints" : [ 0, 0, 0, 0, 1, 1, 1, 1 ]
\t},
\t{
\t\t"Name" : "Categories",
\t\t"IndexedColors" : [ 1, 0, 0, 0, 1, 0 ],
\t\t"Annotations" : [ "0", "zero", "1", "one" ]
\t}
]
"""

# A transfer function exported from a ParaView session: data units, opacity with midpoint/sharpness,
# the extra keys a session export carries.
SESSION_EXPORT = """[
    {
        "AnnotatedValues" : [],
        "Annotations" : [],
        "ColorSpace" : "Diverging",
        "DefaultMap" : false,
        "IndexedColors" : [],
        "IndexedOpacities" : [],
        "Name" : "density session",
        "NanColor" : [1.0, 1.0, 0.0],
        "NanOpacity" : 1.0,
        "Points" : [0.5, 0.0, 0.5, 0.0, 2.0, 0.0, 0.5, 0.0, 3.5, 0.8, 0.25, 0.3],
        "RGBPoints" : [0.5, 0.23137254902, 0.298039215686, 0.752941176471, 3.5, 0.705882352941, 0.0156862745098, 0.149019607843]
    }
]
"""


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_preset_on_unit_range_is_stretched_to_the_data(tmp_path):
    path = _write(tmp_path, "presets.json", PRESET_FILE)
    presets = read_presets(path)
    assert [p.name for p in presets] == ["Blue to Gold", "Black, White"]  # categorical one skipped
    assert presets[0].color_map.color_space == "Lab"
    tf = load_transfer_function(path, (100.0, 300.0))
    assert tf.value_range == (100.0, 300.0)
    assert [p[0] for p in tf.color_map.points] == [100.0, 200.0, 300.0]
    assert tf.color_map.nan_color == (0.25, 0.0, 0.0)
    # The node's own colour, through Lab and back with VTK's rounded matrices (off by 2e-5).
    np.testing.assert_allclose(tf.color_map.evaluate(np.array([200.0]))[0], [1.0, 1.0, 1.0], atol=1e-4)
    # No Points in the preset: the default ramp over the data range.
    np.testing.assert_allclose(tf.opacity_map.evaluate(np.array([100.0, 200.0, 300.0])), [0.0, 0.5, 1.0])
    other = load_transfer_function(path, (0.0, 10.0), name="black, white")
    assert other.color_map.color_space == "RGB"
    np.testing.assert_allclose(other.color_map.evaluate(np.array([2.5]))[0], [0.25, 0.25, 0.25])


def test_presets_off_the_unit_span_are_stretched_too(tmp_path):
    # ParaView normalises every preset by its own span when it applies it (Jet spans -1..1, the erdc maps
    # and "Blue Orange (divergent)" other spans); only "use preset range" keeps the positions.
    path = _write(tmp_path, "session.json", SESSION_EXPORT)
    tf = load_transfer_function(path, value_range=(0.0, 100.0))
    assert tf.value_range == (0.0, 100.0)
    assert [p[0] for p in tf.opacity_map.points] == [0.0, 50.0, 100.0]


def test_session_export_keeps_its_data_units_and_opacity(tmp_path):
    path = _write(tmp_path, "session.json", SESSION_EXPORT)
    tf = load_transfer_function(path, value_range=(0.0, 100.0), units="data")
    assert tf.value_range == (0.5, 3.5)
    assert tf.color_map.color_space == "Diverging"
    assert tf.nan_opacity == 1.0
    assert tf.opacity_map.points[2] == (3.5, 0.8, 0.25, 0.3)
    np.testing.assert_allclose(tf.opacity_map.evaluate(np.array([1.0, 2.0])), [0.0, 0.0])
    assert 0.0 < tf.opacity_map.evaluate(np.array([2.5]))[0] < 0.8
    # Forcing "normalized" stretches it like a preset; an explicit rescale moves the opacity along.
    stretched = load_transfer_function(path, (0.0, 30.0), units="normalized")
    assert stretched.value_range == (0.0, 30.0)
    assert [p[0] for p in stretched.opacity_map.points] == [0.0, 15.0, 30.0]


def test_written_transfer_function_reads_back_identically(tmp_path):
    tf = make_transfer_function("plasma", (-1.5, 4.0), opacity=((0.0, 0.0), (0.2, 0.0), (1.0, 0.6)))
    path = save_transfer_function(tf, tmp_path / "mine.json", name="my plasma")
    document = json.loads(path.read_text())
    assert isinstance(document, list) and document[0]["Name"] == "my plasma"
    assert set(document[0]) >= {"Name", "ColorSpace", "RGBPoints", "Points", "NanColor"}
    assert len(document[0]["RGBPoints"]) % 4 == 0 and len(document[0]["Points"]) % 4 == 0
    back = load_transfer_function(path, value_range=(0.0, 1.0), units="data")  # the range is not applied
    assert back.value_range == pytest.approx(tf.value_range)
    xs = np.linspace(-2.0, 4.5, 50)
    np.testing.assert_allclose(back.color_map.evaluate(xs), tf.color_map.evaluate(xs), atol=1e-9)
    np.testing.assert_allclose(back.opacity_map.evaluate(xs), tf.opacity_map.evaluate(xs), atol=1e-9)
    # Stretched (the default) over the range it was saved on, it is the same function again.
    again = make_transfer_function(str(path), (-1.5, 4.0))
    np.testing.assert_allclose(again.color_map.evaluate(xs), tf.color_map.evaluate(xs), atol=1e-9)
    np.testing.assert_allclose(again.opacity_map.evaluate(xs), tf.opacity_map.evaluate(xs), atol=1e-9)


@pytest.mark.parametrize(
    "text, message",
    [
        ("{not json", "not valid JSON"),
        ('[{"Name": "x", "IndexedColors": [1, 0, 0]}]', "no preset with RGBPoints"),
        ('[{"Name": "x", "RGBPoints": [0, 1, 0]}]', "quadruples"),
        ('[{"Name": "x", "RGBPoints": [0, 1, 0, 0, 1, 2, 0, 0]}]', r"\[0, 1\]"),
        ('[{"Name": "x", "ColorSpace": "Lab/CIEDE2000", "RGBPoints": [0, 1, 0, 0, 1, 0, 0, 1]}]', "CIEDE2000"),
        ('[{"Name": "x", "RGBPoints": [0.5, 1, 0, 0, 0.5, 0, 0, 1]}]', "two or more positions"),
        ('[{"Name": "x", "UseLogScale": "yes", "RGBPoints": [0, 1, 0, 0, 1, 0, 0, 1]}]', "UseLogScale"),
        ('[{"Name": "x", "RGBPoints": [0, 1, 0, 0, 1, 0, 0, 1]} /* unclosed', "not valid JSON"),
        ('[{"Name": "x", "RGBPoints": [0, 1, 0, 0, 1, 0, 0, 1], "Points": [0, 2, 0.5, 0]}]', "opacity"),
        ('[{"Name": "x", "RGBPoints": "red"}]', "list of numbers"),
    ],
)
def test_bad_preset_files_raise_a_user_error_naming_the_file(tmp_path, text, message):
    path = _write(tmp_path, "bad.json", text)
    with pytest.raises(ApmgsrnError, match=message) as info:
        load_transfer_function(path, (0.0, 1.0))
    assert "bad.json" in str(info.value)


def test_missing_file_and_unknown_preset_name(tmp_path):
    with pytest.raises(ApmgsrnError, match="no such file"):
        load_transfer_function(tmp_path / "absent.json", (0.0, 1.0))
    path = _write(tmp_path, "presets.json", PRESET_FILE)
    with pytest.raises(ApmgsrnError, match="no preset named 'Jet'"):
        load_transfer_function(path, (0.0, 1.0), name="Jet")


def test_lenient_json_as_paraview_reads_it(tmp_path):
    # ParaView's reader takes comments and trailing commas (its own ColorMaps.json has had a trailing
    # comma); a comma or slash inside a string stays as it is.
    text = """// presets
    [ { "Name": "a, b // c ] /* d */", /* block
        comment */ "ColorSpace": "RGB", "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1,], },
    ]"""
    presets = read_presets(_write(tmp_path, "lenient.json", text))
    assert [p.name for p in presets] == ["a, b // c ] /* d */"]
    assert presets[0].color_map.points == ((0.0, 0.0, 0.0, 0.0), (1.0, 1.0, 1.0, 1.0))


def test_colour_space_is_read_as_paraview_reads_it(tmp_path):
    spaces = ["RGB", "Lab", "HSV", "Diverging", "Step", "CIELAB", "lab", 2, None]
    entries = [
        {"Name": f"s{i}", "RGBPoints": [0, 0, 0, 1, 1, 1, 1, 0], **({} if space is None else {"ColorSpace": space})}
        for i, space in enumerate(spaces)
    ]
    presets = read_presets(_write(tmp_path, "spaces.json", json.dumps(entries)))
    # Exact names and their numbers in ParaView's list; other spellings are RGB, a missing one Diverging
    # (the space of ParaView's default lookup table).
    assert [p.color_map.color_space for p in presets] == [
        "RGB", "Lab", "HSV", "Diverging", "Step", "RGB", "RGB", "Lab", "Diverging"
    ]


def test_use_log_scale_and_hsv_wrap_are_read_both_ways_paraview_reads_them(tmp_path):
    entries = [
        {"Name": "true", "UseLogScale": True, "HSVWrap": True, "RGBPoints": [1, 0, 0, 0, 10, 1, 1, 1, 100, 1, 0, 0]},
        {"Name": "one", "UseLogScale": 1, "HSVWrap": 1, "RGBPoints": [1, 0, 0, 0, 10, 1, 1, 1, 100, 1, 0, 0]},
    ]
    path = _write(tmp_path, "log.json", json.dumps(entries))
    for name in ("true", "one"):
        # Stretched, both normalise in log10: the middle node (a decade of two) lands half way.
        stretched = load_transfer_function(path, (0.0, 50.0), name=name)
        assert [p[0] for p in stretched.color_map.points] == pytest.approx([0.0, 25.0, 50.0])
        assert not stretched.color_map.log_scale
    # Kept in data units, ParaView sets the table's log scale (and HSVWrap) only from a number.
    assert not load_transfer_function(path, None, name="true", units="data").color_map.log_scale
    kept = load_transfer_function(path, None, name="one", units="data")
    assert kept.color_map.log_scale and kept.opacity_map.points[0][0] == 1.0
    assert [p.color_map.hsv_wrap for p in read_presets(path)] == [False, True]


def test_legacy_xml_presets(tmp_path):
    text = """<ColorMaps>
      <ColorMap name="wrapped" space="Wrapped">
        <Point x="2" o="1" r="1" g="0" b="0"/><Point x="-2" o="1" r="0" g="0" b="1"/>
        <NaN r="0.25" g="0.5" b="0.75"/>
      </ColorMap>
      <ColorMap name="categories" indexedLookup="true"><Point r="1" g="0" b="0" o="1"/></ColorMap>
      <ColorMap name="plain"><Point x="0" o="1" r="0" g="0" b="0"/><Point x="1" o="1" r="1" g="1" b="1"/></ColorMap>
    </ColorMaps>"""
    path = _write(tmp_path, "maps.xml", text)
    presets = read_presets(path)
    assert [p.name for p in presets] == ["wrapped", "plain"]  # the categorical one is skipped
    wrapped = presets[0].color_map
    assert (wrapped.color_space, wrapped.hsv_wrap, wrapped.nan_color) == ("HSV", True, (0.25, 0.5, 0.75))
    assert [p[0] for p in wrapped.points] == [-2.0, 2.0]  # sorted by position
    assert presets[1].color_map.color_space == "Diverging"  # no space: the lookup table's default
    tf = make_transfer_function(str(path), (0.0, 10.0), preset_name="plain")
    # Diverging (Msh) from black to white interpolates lightness: half way is a grey of L* 50.
    middle = tf.color_map.evaluate(np.array([5.0]))[0]
    assert np.ptp(middle) < 1e-4 and rgb_to_lab(middle)[0] == pytest.approx(50.0, abs=0.01)
    with pytest.raises(ApmgsrnError, match="categorical"):
        load_transfer_function(path, (0.0, 1.0), name="categories")
    point = '<Point x="a" r="0" g="0" b="0"/>'
    bad = _write(tmp_path, "bad.xml", f'<ColorMaps><ColorMap name="x">{point}</ColorMap></ColorMaps>')
    with pytest.raises(ApmgsrnError, match="not a number"):
        read_presets(bad)
    with pytest.raises(ApmgsrnError, match="not valid XML"):
        read_presets(_write(tmp_path, "broken.xml", "<ColorMaps><ColorMap"))
