"""``train --ratio`` / ``--size`` for every model kind: the model sized from the byte target
(:mod:`apmgsrn.training.sizing`), and the packed file landing within 5 % under the target, on real volumes."""

from __future__ import annotations

import json

import numpy as np
import pytest

import apmgsrn
from apmgsrn.choices import DEFAULT_MODEL, MODEL_KINDS, default_model
from apmgsrn.cli.main import main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.models.registry import preset_config
from apmgsrn.recipes import PACKING
from apmgsrn.training.sizing import config_for_bytes, parameter_count

pytestmark = pytest.mark.usefixtures("one_thread")
SHORT = ["--iterations", "30", "--batch-size", "2048", "--device", "cpu"]


def run_json(argv, capsys) -> tuple[int, dict]:
    capsys.readouterr()
    code = main([*argv, "--json"])
    return code, json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("kind", MODEL_KINDS)
@pytest.mark.parametrize("volume, ratio", [("turbulence_vorticity_48.npy", 100),  # 4,423 bytes
                                           ("turbulence_vorticity_48.npy", 300),  # 1,474 bytes
                                           ("c60_80x64x48_uint8.raw", 40)])       # 6,144 bytes
def test_every_kind_sized_for_a_ratio_lands_within_five_percent_under_it(kind, volume, ratio, test_data, tmp_path,
                                                                           capsys):
    out = tmp_path / "m.apmgsrn"
    code, trained = run_json(["train", str(test_data / volume), "--model", kind, "--ratio", str(ratio), *SHORT,
                              "--out", str(out)], capsys)
    assert code == 0
    target = trained["data_bytes"] / ratio
    assert trained["model_bytes"] == out.stat().st_size
    assert 0.95 * target <= out.stat().st_size <= target
    assert apmgsrn.load(out).description.config.model == kind


def test_a_hybrid_sized_without_domain_levels_packs_loads_and_decodes(test_data, tmp_path, capsys):
    """Below the smallest level table the hybrid is sized with no domain levels (an empty table): it packs to
    within 5 % under its target, verifies and decodes finite values."""
    volume = test_data / "turbulence_vorticity_48.npy"
    target = 48 ** 3 * 4 // 500  # 884 bytes
    assert config_for_bytes(preset_config("hybrid", "small"), target, volume_shape=(48, 48, 48)).encoder.levels == 0
    out = tmp_path / "m.apmgsrn"
    code, trained = run_json(["train", str(volume), "--model", "hybrid", "--size", str(target), *SHORT,
                              "--out", str(out)], capsys)
    assert code == 0 and 0.95 * target <= out.stat().st_size <= target
    assert main(["verify", str(out)]) == 0
    model = apmgsrn.load(out)
    assert model.description.config.encoder.levels == 0
    values = model.predict([[0.0, 0.0, 0.0], [0.5, -0.5, 0.25]])
    assert np.isfinite(values).all()


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_a_larger_budget_never_gets_fewer_parameters(kind):
    shape = (48, 48, 48)
    config = preset_config(kind, "small")
    targets = [1_500 * 1.5**k for k in range(9)]  # 1.5 KB .. 38 KB: a table or decoder step may cost a few %
    counts = [parameter_count(config_for_bytes(config, int(t), volume_shape=shape).fitted_to(shape)) for t in targets]
    assert counts == sorted(counts) and counts[-1] > 4 * counts[0]


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_sized_models_fill_most_of_their_parameter_budget(kind):
    shape = (128, 128, 128)
    config = preset_config(kind, "small")
    for target in (2_796, 8_388, 27_962):  # 3,000, 1,000 and 300:1 of a 128^3 float32 volume
        sized = config_for_bytes(config, target, volume_shape=shape, overhead=500)
        budget = (target - 500) * 8 / 6
        assert 0.55 * budget <= parameter_count(sized.fitted_to(shape)) <= budget


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_a_target_too_small_is_refused_in_one_line_naming_it(kind):
    with pytest.raises(ApmgsrnError) as caught:
        config_for_bytes(preset_config(kind, "small"), 600, volume_shape=(48, 48, 48))
    message = str(caught.value)
    assert "target_bytes=600" in message and "\n" not in message


def test_given_sizes_are_kept():
    hybrid = config_for_bytes(preset_config("hybrid", "small", levels=6, log2_table_size=9), 8_000,
                              fixed=("levels", "log2_table_size"), volume_shape=(48, 48, 48))
    assert (hybrid.encoder.levels, hybrid.encoder.log2_table_size) == (6, 9)
    ngp = config_for_bytes(preset_config("ngp", "small"), 60_000, fixed=("log2_table_size",))
    assert ngp.encoder.log2_table_size == preset_config("ngp", "small").encoder.log2_table_size
    with pytest.raises(ApmgsrnError, match="target_bytes=8000: even the ngp model of the sizes given"):
        config_for_bytes(preset_config("ngp", "small"), 8_000, fixed=("log2_table_size",))


@pytest.mark.parametrize("ratio", [200, 50])  # 2,211 and 8,847 bytes: either side of PACKING.hybrid_min_bytes
def test_train_ratio_of_the_default_kind_through_the_cli(ratio, test_data, tmp_path, capsys):
    volume = test_data / "turbulence_vorticity_48.npy"  # 442,368 bytes
    out = tmp_path / "d.apmgsrn"
    code, trained = run_json(["train", str(volume), "--ratio", str(ratio), *SHORT, "--out", str(out)], capsys)
    assert code == 0
    target = 442_368 / ratio
    assert 0.95 * target <= out.stat().st_size <= target
    assert apmgsrn.load(out).description.config.model == default_model(byte_target=int(target))
    assert trained["packing"]["psnr"] > 0


def test_the_default_kind_of_a_byte_target_follows_its_size():
    assert default_model() == default_model(byte_target=PACKING.hybrid_min_bytes) == DEFAULT_MODEL
    assert default_model(byte_target=PACKING.hybrid_min_bytes - 1) == "apmgsrn"
