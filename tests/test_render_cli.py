"""``apmgsrn render`` end to end: images, comparisons, animations, presets, models and user errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from apmgsrn.cli.main import main

NEGHIP = "neghip_64x64x64_uint8.raw"
SMALL = ["--width", "40", "--height", "32", "--spp", "48", "--macro-cells", "8"]


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _pixels(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)


def test_render_a_volume_to_png_and_json(test_data, tmp_path, capsys):
    out = tmp_path / "neghip.png"
    code, text, _ = _run(
        capsys, "render", str(test_data / NEGHIP), "--out", str(out), *SMALL,
        "--colormap", "viridis", "--opacity", "0,0,0.3,0,1,0.8", "--background", "black", "--json",
    )
    assert code == 0
    report = json.loads(text)
    assert report["field_evaluations"] < report["samples_in_box"]  # skipping and termination did work
    pixels = _pixels(out)
    assert pixels.shape == (32, 40, 3)
    assert (pixels[0, 0] == 0).all()  # black background in the corner
    assert pixels.max() > 100  # the protein is drawn


def test_compare_writes_side_by_side_error_image_and_prints_metrics(test_data, tmp_path, capsys):
    out = tmp_path / "pair.png"
    data = str(test_data / NEGHIP)
    code, text, _ = _run(capsys, "render", data, "--out", str(out), "--compare", data, *SMALL, "--json")
    assert code == 0
    report = json.loads(text)
    # Identical images: PSNR infinite (None). On a GPU the compositing's atomic sums may round the two
    # renders apart in the last bits, which still reads as far over 120 dB.
    assert report["psnr"] is None or report["psnr"] > 120
    assert report["ssim"] == pytest.approx(1.0)
    assert _pixels(out).shape == (32, 2 * 40 + 4, 3)
    error = tmp_path / "pair_error.png"
    assert report["error_image"] == str(error) and _pixels(error).shape == (32, 40, 3)


def test_turntable_gif_has_the_requested_frames(test_data, tmp_path, capsys):
    out = tmp_path / "turn.gif"
    code, _, _ = _run(capsys, "render", str(test_data / NEGHIP), "--out", str(out), *SMALL, "--frames", "3")
    assert code == 0
    with Image.open(out) as gif:
        assert gif.n_frames == 3 and gif.size == (40, 32)
        gif.seek(0)
        first = np.asarray(gif.convert("RGB"), dtype=np.int16)
        gif.seek(1)
        second = np.asarray(gif.convert("RGB"), dtype=np.int16)
    assert np.abs(first - second).max() > 20  # the camera moved


def test_turntable_mp4(test_data, tmp_path, capsys):
    pytest.importorskip("imageio_ffmpeg")
    imageio = pytest.importorskip("imageio.v2")
    out = tmp_path / "turn.mp4"
    code, _, _ = _run(capsys, "render", str(test_data / NEGHIP), "--out", str(out), *SMALL, "--frames", "2")
    assert code == 0
    frames = imageio.mimread(out)
    assert len(frames) == 2 and frames[0].shape == (32, 40, 3)


def test_saved_transfer_function_reproduces_the_image(test_data, tmp_path, capsys):
    data = str(test_data / NEGHIP)
    preset = tmp_path / "tf.json"
    first, second = tmp_path / "a.png", tmp_path / "b.png"
    opts = [*SMALL, "--colormap", "plasma", "--opacity", "0,0,0.25,0,1,0.9", "--range", "10,240"]
    assert _run(capsys, "render", data, "--out", str(first), *opts, "--save-tf", str(preset))[0] == 0
    assert json.loads(preset.read_text())[0]["ColorSpace"] == "RGB"
    # Kept in its data units (ParaView's "use preset range") it needs no range ...
    kept = [*SMALL, "--colormap", str(preset), "--preset-units", "data"]
    assert _run(capsys, "render", data, "--out", str(second), *kept)[0] == 0
    assert np.abs(_pixels(first) - _pixels(second)).max() <= 1
    # ... stretched (the default, as ParaView applies presets) over the range it was saved on, the same.
    third = tmp_path / "c.png"
    stretched = [*SMALL, "--colormap", str(preset), "--range", "10,240"]
    assert _run(capsys, "render", data, "--out", str(third), *stretched)[0] == 0
    assert np.abs(_pixels(first) - _pixels(third)).max() <= 1


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--opacity", "0,0,1"], "--opacity"),
        (["--opacity", "0.5,0,0.2,1"], "increasing"),
        (["--range", "5,1"], "--range"),
        (["--background", "purple"], "--background"),
        (["--colormap", "nonexistent"], "unknown colour map"),
        (["--spp", "0"], "--spp"),
        (["--frames", "2"], ".gif or .mp4"),
    ],
)
def test_user_errors_exit_2_with_one_line(test_data, tmp_path, capsys, extra, message):
    code, _, err = _run(capsys, "render", str(test_data / NEGHIP), "--out", str(tmp_path / "x.png"), *SMALL, *extra)
    assert code == 2
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


def test_missing_input_and_bad_output_suffix(tmp_path, capsys):
    code, _, err = _run(capsys, "render", str(tmp_path / "none.nc"), "--out", str(tmp_path / "x.png"))
    assert code == 2 and "none.nc" in err
    code, _, err = _run(capsys, "render", str(tmp_path / "none.nc"), "--out", str(tmp_path / "x.jpg"))
    assert code == 2 and ".png" in err


def test_render_a_trained_model_against_its_volume(test_data, tmp_path, capsys):
    pytest.importorskip("apmgsrn.training.checkpoint")
    model = tmp_path / "neghip.apm"
    data = str(test_data / NEGHIP)
    code, _, err = _run(
        capsys, "train", data, "--out", str(model), "--preset", "small", "--iterations", "100", "--batch-size", "4096",
        "--device", "cpu",
    )
    assert code == 0, err
    out = tmp_path / "model.png"
    code, text, err = _run(
        capsys, "render", str(model), "--out", str(out), "--compare", data, *SMALL,
        "--opacity", "0,0,0.3,0,1,0.8", "--json",
    )
    assert code == 0, err
    report = json.loads(text)
    # A 100-iteration small model already gives a recognisable image (measured once: 30.9 dB, SSIM 0.937).
    assert report["psnr"] > 25.0 and report["ssim"] > 0.85
    assert report["visible_cells"] < 1.0  # bounds sampled from the model let it skip space
