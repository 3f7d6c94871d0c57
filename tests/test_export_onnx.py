"""``apmgsrn export --format onnx``: the graph ONNX Runtime runs gives PyTorch's values on random points.

Models: the reference field and brick model of tests/data (trained on the real neghip volume), the brick
model both routed and blended, and a fresh fit with a log10 value transform (the inverse transform is part of
the graph).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import pytest
import torch

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.export import EveryBrick, _portable


def _onnx_values(session: onnxruntime.InferenceSession, points: np.ndarray) -> np.ndarray:
    (values,) = session.run(["values"], {"points": points})
    return values[:, 0]


def _random_points(count: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (count, 3)).astype(np.float32)


def _check(model: apmgsrn.Model, onnx_path: Path) -> None:
    span = model.description.value_range[1] - model.description.value_range[0]
    # One session for all (building one takes seconds for a hybrid model's graph).
    session = onnxruntime.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    for seed, count in ((0, 1), (1, 777), (2, 20000)):  # the graph takes any number of points
        points = _random_points(count, seed)
        np.testing.assert_allclose(_onnx_values(session, points), model.predict(points), rtol=0, atol=1e-5 * span)


@pytest.mark.parametrize("name", ["reference_field.apmgsrn", "reference_bricks"])
def test_cli_export_matches_pytorch(test_data: Path, tmp_path: Path, name: str) -> None:
    out = tmp_path / "model.onnx"
    assert main(["export", str(test_data / name), "--format", "onnx", "--out", str(out)]) == 0
    onnx.checker.check_model(str(out))
    graph = onnx.load(str(out)).graph
    assert [i.name for i in graph.input] == ["points"] and [o.name for o in graph.output] == ["values"]
    _check(apmgsrn.load(test_data / name), out)


def test_blended_brick_model_exports_blending(test_data: Path, tmp_path: Path) -> None:
    model = apmgsrn.load(test_data / "reference_bricks")
    model.field.blend = True
    out = model.export_onnx(tmp_path / "blended.onnx")
    _check(model, out)
    # The traceable form is the routed model's arithmetic, points on brick borders and outside the box too.
    points = torch.cat([torch.from_numpy(_random_points(4000, 3)) * 1.2,
                        torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 0.5], [-0.0417, 0.3, 0.3]])])
    for blend in (False, True):
        model.field.blend = blend
        every = _portable(model.field)
        assert isinstance(every, EveryBrick)
        with torch.no_grad():
            torch.testing.assert_close(every(points), model.field(points), rtol=0, atol=1e-5 * 255)


def test_log_transform_model_exports_its_inverse(test_data: Path, tmp_path: Path, one_thread) -> None:
    from apmgsrn.data import open_volume

    density = open_volume(test_data / "darkmatter_density_64.h5").to_numpy()[:24, :24, :24]  # 0.23 .. 1e5
    # The default model kind (hybrid) with few hash levels: its graph grows with them, and export and ONNX
    # Runtime's session took 40 s at the default levels for what four levels check as well.
    model = apmgsrn.fit(density, transform="log10", iterations=40, batch_size=2048, grids=4, resolution=8,
                        width=16, levels=4, log2_table_size=10, progress=False)
    path = tmp_path / "log.apmgsrn"
    model.save(path)
    out = tmp_path / "log.onnx"
    assert main(["export", str(path), "--out", str(out)]) == 0
    _check(apmgsrn.load(path), out)


def test_export_refuses_to_replace_the_model(test_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "m.apmgsrn"
    model.write_bytes((test_data / "reference_field.apmgsrn").read_bytes())
    assert main(["export", str(model), "--out", str(model)]) == 2
    assert "--out" in capsys.readouterr().err
    assert model.read_bytes() == (test_data / "reference_field.apmgsrn").read_bytes()
