"""The notebook API at the package's top level: fit a numpy array, an xarray DataArray or a file; predict
(numpy in, numpy out, no gradient); decode to a labelled array; save and load; render an RGBA image.

Data: the real neghip volume (tests/data); the DataArray test wraps the real Miranda crop with the labels a
notebook user would give it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import xarray

import apmgsrn

SMALL = dict(iterations=60, batch_size=4096, grids=4, resolution=8, width=16, progress=False)


@pytest.fixture(scope="module")
def neghip(test_data: Path) -> np.ndarray:
    return np.load(test_data / "neghip_32x32x32_uint8.npy")  # [32, 32, 32] uint8


@pytest.fixture(scope="module")
def fitted(neghip: np.ndarray, one_thread) -> apmgsrn.Model:
    return apmgsrn.fit(neghip, preset="small", device="cpu", **SMALL)


def test_three_lines_fit_predict_decode(fitted: apmgsrn.Model, neghip: np.ndarray) -> None:
    # The notebook's three lines are apmgsrn.fit (the fixture), predict and decode.
    points = np.random.default_rng(0).uniform(-1, 1, (500, 3))
    values = fitted.predict(points)
    decoded = fitted.decode()
    assert isinstance(values, np.ndarray) and values.shape == (500,) and values.dtype == np.float32
    assert isinstance(decoded, xarray.DataArray) and decoded.shape == neghip.shape
    # The fit is a fit: it follows the data far better than its mean does.
    truth = neghip.astype(np.float32)
    error = np.sqrt(np.mean((decoded.values - truth) ** 2))
    assert error < 0.5 * np.std(truth)
    # predict and decode agree at the voxels, and predict is the network's own value.
    z, y, x = 3, 17, 29
    voxel = np.array([[-1 + 2 * x / 31, -1 + 2 * y / 31, -1 + 2 * z / 31]])
    assert fitted.predict(voxel)[0] == pytest.approx(float(decoded.values[z, y, x]), abs=1e-4)
    with torch.no_grad():
        direct = fitted(torch.from_numpy(points).float()).numpy()[:, 0]
    np.testing.assert_allclose(values, direct, atol=1e-5)
    assert fitted.description.training["psnr"] == pytest.approx(
        20 * np.log10(float(np.ptp(truth))) - 10 * np.log10(np.mean((decoded.values - truth) ** 2)), abs=0.05)


def test_predict_takes_any_leading_shape_and_no_gradient(fitted: apmgsrn.Model) -> None:
    grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, 5)] * 3, indexing="ij"), -1)  # [5, 5, 5, 3]
    values = fitted.predict(grid)
    assert values.shape == (5, 5, 5)
    np.testing.assert_array_equal(values.reshape(-1), fitted.predict(grid.reshape(-1, 3)))
    tensor = torch.from_numpy(grid.reshape(-1, 3)).float().requires_grad_()
    assert isinstance(fitted.predict(tensor), np.ndarray)  # no grad error, numpy out
    with pytest.raises(apmgsrn.ApmgsrnError, match=r"\[\.\.\., 3\]"):
        fitted.predict(np.zeros((4, 2)))


def test_decode_without_xarray_gives_numpy(fitted: apmgsrn.Model, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "xarray", None)  # makes `import xarray` fail
    decoded = fitted.decode(shape=(4, 5, 6))
    assert type(decoded) is np.ndarray and decoded.shape == (4, 5, 6)


def test_save_and_load_give_the_same_model(fitted: apmgsrn.Model, tmp_path: Path) -> None:
    path = fitted.save(tmp_path / "neghip.apmgsrn")
    loaded = apmgsrn.load(path, device="cpu")
    points = np.random.default_rng(1).uniform(-1, 1, (300, 3))
    np.testing.assert_array_equal(loaded.predict(points), fitted.predict(points))
    assert loaded.description.source.dtype == "uint8"
    (tmp_path / "notes.txt").write_text("keep me")
    with pytest.raises(apmgsrn.ApmgsrnError, match="not an apmgsrn model"):
        fitted.save(tmp_path / "notes.txt")
    assert (tmp_path / "notes.txt").read_text() == "keep me"


def test_fit_a_data_array_keeps_its_labels(test_data: Path, one_thread) -> None:
    from apmgsrn.data import open_volume

    values = open_volume(test_data / "miranda_density_80x64x48.nc").to_numpy()  # [48, 64, 80]
    array = xarray.DataArray(
        values, name="density", dims=("z", "y", "x"),
        coords={"x": np.linspace(0.0, 7.9, 80), "y": ("y", np.linspace(-1, 1, 64), {"units": "m"})},
        attrs={"units": "g/cm^3", "long_name": "mixing density"},
    )
    model = apmgsrn.fit(array, **SMALL)
    decoded = model.decode(shape=(48, 32, 40))
    assert decoded.name == "density" and decoded.attrs == {"units": "g/cm^3", "long_name": "mixing density"}
    assert decoded.dims == ("z", "y", "x")
    np.testing.assert_allclose(decoded["x"].values, np.linspace(0.0, 7.9, 40))
    assert decoded["y"].attrs == {"units": "m"}
    np.testing.assert_allclose(decoded["z"].values, np.arange(48))  # no z coordinate: voxel indices
    whole = model.decode()
    assert np.sqrt(np.mean((whole.values - values) ** 2)) < 0.5 * np.std(values)


def test_fit_takes_a_path_and_time_of_a_four_d_array(test_data: Path) -> None:
    with pytest.raises(apmgsrn.ApmgsrnError, match="time="):
        apmgsrn.fit(xarray.DataArray(np.zeros((2, 4, 4, 4)), dims=("t", "z", "y", "x")), **SMALL)
    with pytest.raises(apmgsrn.ApmgsrnError, match="variable="):
        apmgsrn.fit(np.zeros((4, 4, 4)), variable="x", **SMALL)
    with pytest.raises(apmgsrn.ApmgsrnError, match="no such file"):
        apmgsrn.fit(test_data / "missing.nc", **SMALL)
    with pytest.raises(apmgsrn.ApmgsrnError, match="iterations"):
        apmgsrn.fit(np.zeros((4, 4, 4)), iterations=0, progress=False)


def test_render_returns_an_rgba_image(fitted: apmgsrn.Model) -> None:
    image = apmgsrn.render(fitted, width=40, height=30, samples_per_ray=64)
    assert image.shape == (30, 40, 4) and image.dtype == np.uint8
    alpha = image[..., 3]
    assert alpha[0, 0] == 0 and alpha[15, 20] > 0  # the corner misses the box, the centre looks through it
    # Colour over white equals the RGB render over the (default white) background.
    from apmgsrn.rendering import Camera, RendererConfig, VolumeRenderer, extent_from_shape, make_transfer_function

    extent = extent_from_shape(fitted.description.volume_shape)
    tf = make_transfer_function("Cool to Warm", fitted.description.value_range)
    rgb = VolumeRenderer(fitted.field, tf, RendererConfig(samples_per_ray=64), extent=extent).render(
        Camera.orbit(width=40, height=30, extent=extent)).image.numpy()
    a = image[..., 3:].astype(np.float64) / 255
    over_white = image[..., :3] / 255 * a + (1 - a)
    assert np.abs(over_white - rgb).max() < 3 / 255


def test_import_stays_light_and_names_resolve() -> None:
    code = ("import sys, json, apmgsrn; light = 'torch' not in sys.modules; "
            "names = [callable(getattr(apmgsrn, n)) for n in ('fit', 'load', 'render', 'Model', 'Region')]; "
            "print(json.dumps({'light': light, 'names': names}))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == {"light": True, "names": [True] * 5}
