"""Shared fixtures: the small real volumes the repo carries (tests/data, and the demo's examples/data)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from apmgsrn.data import open_volume

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def test_data() -> Path:
    """Folder of the small real volumes bundled with the tests (provenance and cuts: tests/data/README.md)."""
    return REPO / "tests" / "data"


@pytest.fixture(scope="session")
def hcci_oh() -> Path:
    """The 187^3 HCCI OH field (NetCDF4, variable ``oh``) that the repo ships for its demo, used as is."""
    return REPO / "examples" / "data" / "hcci_oh_187.nc"


@pytest.fixture(scope="module")
def neghip_crop(test_data, tmp_path_factory):
    """A real 24^3 crop of the neghip protein field, as .npy (small enough for quick CPU runs): (path, data)."""
    volume = open_volume(test_data / "neghip_64x64x64_uint8.raw")
    data = volume.read(slice(20, 44), slice(20, 44), slice(20, 44))
    path = tmp_path_factory.mktemp("neghip") / "neghip_crop.npy"
    np.save(path, data)
    return path, data


@pytest.fixture
def vector_unit(monkeypatch):
    """The fused training step's decoder products on the vector unit in float32: where the CPU has AMX the step
    takes its tile unit, whose bfloat16 pieces tests/test_ops_tile_products_cpu.py compares on their own terms."""
    from apmgsrn.ops import field_train_cpu

    monkeypatch.setattr(field_train_cpu, "tile_unit_takes", lambda *args: False)


@pytest.fixture(scope="module")
def one_thread():
    """Run a module on one thread: small batches gain nothing from a second one and lose a lot on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def _deterministic_threads():
    torch.manual_seed(0)
    yield


def pytest_collection_modifyitems(config, items):
    has_cuda = torch.cuda.is_available()
    chromium = Path("/usr/bin/chromium").exists()
    pvpython = shutil.which("pvpython") is not None
    for item in items:
        if "gpu" in item.keywords and not has_cuda:
            item.add_marker(pytest.mark.skip(reason="needs a CUDA device"))
        if "browser" in item.keywords and not chromium:
            item.add_marker(pytest.mark.skip(reason="needs /usr/bin/chromium"))
        if "paraview" in item.keywords and not pvpython:
            item.add_marker(pytest.mark.skip(reason="needs ParaView's pvpython on PATH (Debian: apt-get install paraview)"))


@pytest.fixture(scope="module")
def client():
    """An in-process Dask cluster of two one-thread workers, shared by a test module's brick runs."""
    import distributed

    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0",
                                       worker_dashboard_address=None)
    with distributed.Client(cluster) as c:
        yield c
    cluster.close()
