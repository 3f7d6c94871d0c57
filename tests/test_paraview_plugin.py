"""The ParaView reader plugin, in ParaView itself: Debian's ``pvpython`` loads
``src/apmgsrn/paraview_plugin/apmgsrn_reader.py``, opens models by file name (as the File > Open dialog does)
and the array, name, origin and spacing it gets equal ``apmgsrn decode``'s (values to 1e-5 of the value range).

Models: one fitted here on the real viscous-fingering ``.vti`` crop (origin 16, 16, 32: a placed volume) and
the reference brick model of tests/data (opened through its manifest.json). Marker ``paraview``: skipped
without ``pvpython`` (Debian's ``paraview`` package, installed by scripts/test.sh).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import apmgsrn
from apmgsrn.cli.main import main

pytestmark = pytest.mark.paraview

REPO = Path(__file__).resolve().parents[1]
PLUGIN = REPO / "src" / "apmgsrn" / "paraview_plugin" / "apmgsrn_reader.py"
SCRIPT = Path(__file__).parent / "paraview_scripts" / "read_model.py"


@pytest.fixture(scope="module")
def fingers_model(tmp_path_factory, test_data: Path, one_thread) -> Path:
    path = tmp_path_factory.mktemp("model") / "fingers.apmgsrn"
    apmgsrn.fit(test_data / "viscous_fingers_run01" / "030_density_030_064_2.0.vti", iterations=40,
                batch_size=2048, grids=4, resolution=8, width=16, progress=False).save(path)
    return path


def _decode(model: Path, folder: Path, options: list[str]) -> tuple[np.ndarray, dict]:
    """apmgsrn decode's array and its report (name, origin, spacing) for the same settings."""
    out = folder / "decoded.npy"
    assert main(["decode", str(model), "--out", str(out), "--device", "cpu", *options]) == 0
    report = folder / "report.json"
    with open(report, "w") as handle:
        sys.stdout, saved = handle, sys.stdout
        try:
            assert main(["decode", str(model), "--out", str(folder / "plan.vti"), "--dry-run", "--json",
                         *options]) == 0
        finally:
            sys.stdout = saved
    return np.load(out), json.loads(report.read_text())


def test_pvpython_reads_what_decode_writes(fingers_model: Path, test_data: Path, tmp_path: Path) -> None:
    cases = [
        (fingers_model, {}, []),
        (fingers_model, {"resolution": [10, 12, 20], "region": [2, 20, 0, -1, 3, 30]},
         ["--shape", "10,12,20", "--region", "2:21,:,3:31"]),
        (test_data / "reference_bricks" / "manifest.json", {}, []),
    ]
    requests = []
    for index, (model, settings, _) in enumerate(cases):
        out = tmp_path / f"paraview{index}"
        out.mkdir()
        requests.append({"file": str(model), "out": str(out), **settings})
    (tmp_path / "requests.json").write_text(json.dumps(requests))
    # The plugin runs apmgsrn in this interpreter's environment (this checkout's source); ParaView keeps its own.
    env = {**os.environ, "APMGSRN_PYTHON": sys.executable, "APMGSRN_PYTHONPATH": str(REPO / "src"),
           "HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / "config"), "TMPDIR": str(tmp_path / "tmp")}
    (tmp_path / "tmp").mkdir()
    env.pop("PYTHONPATH", None)
    done = subprocess.run([shutil.which("pvpython"), str(SCRIPT), str(PLUGIN), str(tmp_path / "requests.json")],
                          env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert list((tmp_path / "tmp").glob("apmgsrn-paraview-*")) == []  # no decoded volume left behind

    for index, (model, _, options) in enumerate(cases):
        folder = tmp_path / f"paraview{index}"
        grid = json.loads((folder / "grid.json").read_text())
        theirs = np.load(folder / "values.npy")
        ours, report = _decode(model.parent if model.name == "manifest.json" else model, folder, options)
        assert grid["reader"] == "ApmgsrnReader" and grid["arrays"] == 1
        assert grid["name"] == report["variable"]
        assert grid["dimensions"] == report["shape_xyz"] == list(reversed(ours.shape))
        assert grid["origin"] == pytest.approx(report["origin"], abs=1e-9)
        assert grid["spacing"] == pytest.approx(report["spacing"], rel=1e-12)
        low, high = report["value_range"]
        np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-5 * (high - low))

    # The fitted volume keeps its file's name and place: ImageFile, origin (16, 16, 32), unit spacing.
    first = json.loads((tmp_path / "paraview0" / "grid.json").read_text())
    assert first["name"] == "ImageFile" and first["origin"] == [16.0, 16.0, 32.0] and first["spacing"] == [1, 1, 1]
    # The region starts at voxel (2, 0, 3) of the volume, in its coordinates.
    second = json.loads((tmp_path / "paraview1" / "grid.json").read_text())
    assert second["origin"] == [18.0, 16.0, 35.0]
