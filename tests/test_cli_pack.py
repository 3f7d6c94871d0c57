"""``train --bits/--max-error``, ``pack``, and what ``info``, ``eval``, ``decode`` and ``render`` do with a packed
file, on a real volume (neghip, 32^3 crop)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.sources import open_source

pytestmark = pytest.mark.usefixtures("one_thread")
TINY = ["--grids", "4", "--resolution", "8", "--features", "2", "--width", "16", "--iterations", "40",
        "--batch-size", "2048", "--decoder-precision", "float32", "--device", "cpu"]


@pytest.fixture(scope="module")
def neghip(test_data):
    return test_data / "neghip_32x32x32_uint8.npy"


@pytest.fixture(scope="module")
def float32_model(neghip, tmp_path_factory):
    out = tmp_path_factory.mktemp("pack") / "f.apmgsrn"
    assert main(["train", str(neghip), "--out", str(out), *TINY, "--json"]) == 0
    return out


def run_json(argv, capsys) -> tuple[int, dict]:
    capsys.readouterr()
    code = main([*argv, "--json"])
    return code, json.loads(capsys.readouterr().out)


def test_train_with_a_bound_packs_and_every_command_reads_the_file(neghip, tmp_path, capsys):
    out = tmp_path / "b.apmgsrn"
    code, trained = run_json(["train", str(neghip), "--out", str(out), *TINY, "--bits", "8", "--max-error", "4"],
                             capsys)
    assert code == 0 and trained["packing"]["bits"] == 8 and trained["model_bytes"] == out.stat().st_size
    # The default model stores its tables in float16 already: 8 bits and coding halve it at least.
    network_bytes = trained["model_bytes"] - trained["packing"]["corrected_voxels"] * 4
    assert trained["unpacked_model_bytes"] > 2 * network_bytes
    assert not (tmp_path / "b.apmgsrn.ckpt").exists()
    # info: bytes per part and the PSNR cost measured at pack time.
    code, info = run_json(["info", str(out)], capsys)
    packing = info["packing"]
    assert code == 0 and packing["max_error"] == 4 and packing["report"]["psnr_cost"] == trained["packing"]["psnr_cost"]
    assert sum(p["bytes"] for p in packing["parts"]) + packing["container_bytes"] == out.stat().st_size
    # eval verifies the bound on every voxel and reports what it costs.
    code, figures = run_json(["eval", str(out), str(neghip)], capsys)
    assert code == 0 and figures["bound_holds"] and figures["max_abs_error"] <= 4
    assert figures["correction_bytes"] == packing["correction_bytes"] > 0
    # decode: every voxel within the bound.
    decoded = tmp_path / "d.npy"
    assert main(["decode", str(out), "--out", str(decoded)]) == 0
    truth = np.load(neghip).astype(np.float64)
    assert np.abs(np.load(decoded).astype(np.float64) - truth).max() <= 4
    # render: the packed, corrected field draws like any model.
    image = tmp_path / "r.png"
    assert main(["render", str(out), "--out", str(image), "--width", "48", "--height", "48", "--spp", "32",
                 "--reference-samples", "32", "--device", "cpu"]) == 0
    assert image.stat().st_size > 0
    # The viewer opens models through the same render source.
    source = open_source(out)
    assert source.kind == "model" and "packed, |error| <= 4 at every voxel" in source.description
    points = torch.rand(1000, 3) * 2 - 1
    with torch.no_grad():
        assert torch.equal(source.field(points), apmgsrn.load(out)(points))


def test_eval_on_another_volume_reports_the_bound_violated(float32_model, neghip, test_data, tmp_path, capsys):
    out = tmp_path / "b.apmgsrn"
    assert main(["pack", str(float32_model), str(neghip), "--out", str(out), "--max-error", "2"]) == 0
    other = test_data / "viscous_fingers_run01" / "030_density_030_064_2.0.vti"  # also 32^3
    code, figures = run_json(["eval", str(out), str(other)], capsys)
    assert code == 1 and figures["bound_holds"] is False


def test_pack_to_a_ratio_lands_at_or_under_it(float32_model, neghip, tmp_path, capsys):
    out = tmp_path / "r.apmgsrn"
    code, packed = run_json(["pack", str(float32_model), str(neghip), "--out", str(out), "--ratio", "8"], capsys)
    stored = 32**3  # uint8
    assert code == 0 and packed["file_bytes"] == out.stat().st_size <= stored / 8
    assert packed["compression_ratio"] >= 8 and packed["mode"] == "size"
    assert apmgsrn.load(out).description.packing.report["target_bytes"] == stored // 8


@pytest.mark.parametrize("argv, message", [
    (["--bits", "40"], "--bits"),
    (["--bits", "8", "--size", "5000"], "--bits 8 and --size 5000"),
    (["--size", "5000", "--ratio", "10"], "--size and --ratio"),
    (["--ratio", "-3"], "--ratio: -3: must be a finite number > 0"),
    (["--max-error", "0"], "--max-error"),
    (["--qat-iterations", "5", "--bits", "32"], "--qat-iterations"),
    (["--size", "50"], "--size 50: even with every parameter at its coarsest"),
])
def test_bad_packing_options_are_one_line_errors(float32_model, neghip, tmp_path, capsys, argv, message):
    out = tmp_path / "x.apmgsrn"
    assert main(["pack", str(float32_model), str(neghip), "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err and not out.exists()


def test_pack_refuses_to_write_onto_its_inputs_and_train_refuses_bricks(float32_model, neghip, tmp_path, capsys):
    assert main(["pack", str(float32_model), str(neghip), "--out", str(neghip)]) == 2
    assert "would destroy the input" in capsys.readouterr().err
    assert main(["train", str(neghip), "--out", str(tmp_path / "b"), "--bricks", "2,1,1", "--bits", "8"]) == 2
    assert "single models" in capsys.readouterr().err


def test_pack_refuses_a_volume_of_another_shape(float32_model, test_data, tmp_path, capsys):
    assert main(["pack", str(float32_model), str(test_data / "reference_neghip_24.npy"), "--out",
                 str(tmp_path / "x.apmgsrn")]) == 2
    assert "the model was trained on" in capsys.readouterr().err


def test_train_to_a_ratio_chooses_the_model_size_and_lands_under_it(neghip, tmp_path, capsys):
    out = tmp_path / "r.apmgsrn"
    small = ["--model", "apmgsrn", *(a for a in TINY if a not in ("--resolution", "8"))]
    code, trained = run_json(["train", str(neghip), "--out", str(out), *small, "--ratio", "20"], capsys)
    assert code == 0 and trained["model_bytes"] == out.stat().st_size <= 32**3 / 20
    chosen = apmgsrn.load(out).description.config.encoder.resolution
    assert chosen != (16, 16, 16)  # not the preset's: the size was chosen for the target
    code, larger = run_json(["train", str(neghip), "--out", str(tmp_path / "l.apmgsrn"), *small, "--ratio", "5"],
                            capsys)
    assert apmgsrn.load(tmp_path / "l.apmgsrn").description.config.encoder.resolution[0] > chosen[0]


def test_a_tiny_size_target_shrinks_the_decoder_and_the_grid_count_unless_they_were_given():
    from apmgsrn.models.registry import preset_config
    from apmgsrn.recipes import PACKING
    from apmgsrn.training.packing import packed_overhead
    from apmgsrn.training.sizing import config_for_bytes

    def estimate(config):
        parameters = sum(int(np.prod(shape)) for shape in config.parameter_shapes().values())
        return parameters * PACKING.bits_per_parameter / 8 + packed_overhead(small)

    small = preset_config("apmgsrn", "small")
    large = config_for_bytes(small, 300_000)  # about 90:1 on a 256^3 uint8 volume: the preset's shape
    assert (large.encoder.grids, large.decoder.hidden_layers, large.decoder.width) == (16, 2, 64)
    tiny = config_for_bytes(small, 2_600)  # 10,000:1 on a 187^3 float32 volume
    assert tiny.encoder.grids < 16 and tiny.decoder.width < 64
    assert tiny.encoder.resolution[0] >= 6
    for config, target in ((large, 300_000), (tiny, 2_600)):
        assert estimate(config) <= target
    kept = config_for_bytes(small, 8_000, fixed=("grids", "decoder"))
    assert (kept.encoder.grids, kept.decoder.hidden_layers, kept.decoder.width) == (16, 2, 64)
    free = config_for_bytes(small, 8_000)
    assert free.decoder.width < 64 and min(free.encoder.resolution) > min(kept.encoder.resolution)


def test_train_to_a_tiny_ratio_lands_under_it_with_a_smaller_decoder(test_data, tmp_path, capsys):
    volume = test_data / "neghip_64x64x64_uint8.raw"  # 262,144 bytes: 100:1 leaves 2,621
    out = tmp_path / "t.apmgsrn"
    code, trained = run_json(["train", str(volume), "--out", str(out), "--iterations", "40", "--batch-size", "2048",
                              "--device", "cpu", "--ratio", "100"], capsys)
    assert code == 0 and trained["model_bytes"] == out.stat().st_size <= 64**3 / 100
    model = apmgsrn.load(out)
    assert model.description.config.decoder.width < 64
    assert trained["packing"]["psnr"] > 18  # the best constant (its mean) scores 15.1 dB


def test_a_ratio_no_model_reaches_is_a_clear_error(neghip, tmp_path, capsys):
    assert main(["train", str(neghip), "--out", str(tmp_path / "x.apmgsrn"), *TINY[4:], "--ratio", "5000"]) == 2
    err = capsys.readouterr().err
    assert "even grids of 2^3" in err and "a lower ratio" in err
