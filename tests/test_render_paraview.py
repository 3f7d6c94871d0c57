"""ParaView colour-map presets: parsing presets and session exports, errors, and writing them back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from apmgsrn.errors import ApmgsrnError
from apmgsrn.render.colormaps import make_transfer_function
from apmgsrn.render.paraview import load_transfer_function, read_presets, save_transfer_function

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
    assert presets[0].color_map.color_space == "Lab" and presets[0].is_normalized
    tf = load_transfer_function(path, (100.0, 300.0))
    assert tf.value_range == (100.0, 300.0)
    assert [p[0] for p in tf.color_map.points] == [100.0, 200.0, 300.0]
    assert tf.color_map.nan_color == (0.25, 0.0, 0.0)
    np.testing.assert_allclose(tf.color_map.evaluate(np.array([200.0]))[0], [1.0, 1.0, 1.0], atol=1e-9)
    # No Points in the preset: the default ramp over the data range.
    np.testing.assert_allclose(tf.opacity_map.evaluate(np.array([100.0, 200.0, 300.0])), [0.0, 0.5, 1.0])
    other = load_transfer_function(path, (0.0, 10.0), name="black, white")
    assert other.color_map.color_space == "RGB"
    np.testing.assert_allclose(other.color_map.evaluate(np.array([2.5]))[0], [0.25, 0.25, 0.25])


def test_session_export_keeps_its_data_units_and_opacity(tmp_path):
    path = _write(tmp_path, "session.json", SESSION_EXPORT)
    tf = load_transfer_function(path, value_range=(0.0, 100.0))  # auto: not on [0, 1], so kept
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
    back = load_transfer_function(path, value_range=(0.0, 1.0))  # data units: the range is not applied
    assert back.value_range == pytest.approx(tf.value_range)
    xs = np.linspace(-2.0, 4.5, 50)
    np.testing.assert_allclose(back.color_map.evaluate(xs), tf.color_map.evaluate(xs), atol=1e-9)
    np.testing.assert_allclose(back.opacity_map.evaluate(xs), tf.opacity_map.evaluate(xs), atol=1e-9)
    # The same file through the renderer's entry point gives the same function.
    again = make_transfer_function(str(path), (0.0, 1.0))
    np.testing.assert_allclose(again.opacity_map.evaluate(xs), tf.opacity_map.evaluate(xs), atol=1e-9)


@pytest.mark.parametrize(
    "text, message",
    [
        ("{not json", "not valid JSON"),
        ('[{"Name": "x", "IndexedColors": [1, 0, 0]}]', "no preset with RGBPoints"),
        ('[{"Name": "x", "RGBPoints": [0, 1, 0]}]', "quadruples"),
        ('[{"Name": "x", "RGBPoints": [0, 1, 0, 0, 1, 2, 0, 0]}]', r"\[0, 1\]"),
        ('[{"Name": "x", "ColorSpace": "Wavelet", "RGBPoints": [0, 1, 0, 0, 1, 0, 0, 1]}]', "colour space"),
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
