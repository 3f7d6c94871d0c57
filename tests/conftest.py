"""Shared fixtures: the real sample volumes in ../shared/data and a bundled copy in the repo."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("APMGSRN_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder of the real sample volumes (``../shared/data``); skip if this checkout has none."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"no shared data folder at {SHARED_DATA}")
    return SHARED_DATA


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
