"""Outputs on full disks, read-only or odd targets: one line, exit code 2, and nothing partial left under a
final name (or anywhere)."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from apmgsrn.cli.main import main
from apmgsrn.data.writers import VolumeWriter
from apmgsrn.io import container


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("model")
    data = folder / "v.npy"
    np.save(data, np.random.default_rng(0).random((10, 11, 12), dtype=np.float32))
    out = folder / "m.apmgsrn"
    assert main(["train", str(data), "--out", str(out), "--iterations", "3", "--grids", "2", "--resolution", "4"]) == 0
    return out


def one_line_error(capsys, *words: str) -> str:
    """The error: the last line of stderr, alone (progress lines may come before it), no traceback."""
    err = capsys.readouterr().err
    last = err.rstrip("\n").splitlines()[-1]
    assert last.startswith("error: ") and err.count("error: ") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in last, err
    return last


@pytest.mark.parametrize("suffix", [".npy", ".raw", ".nc"])
def test_decode_onto_a_disk_without_room_is_refused_and_leaves_nothing(model, tmp_path, monkeypatch, suffix,
                                                                       capsys):
    if suffix != ".nc":  # raw/.npy sizes are exact: refused before the first byte
        monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10**9, 10**9 - 100, 100))
    else:  # NetCDF: the write itself fails as on a full disk
        def full(self, z, block):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        monkeypatch.setattr(VolumeWriter, "_store", full)
    out = tmp_path / f"decoded{suffix}"
    assert main(["decode", str(model), "--out", str(out)]) == 2
    one_line_error(capsys, str(out))
    assert list(tmp_path.iterdir()) == []


def test_a_write_that_fails_half_way_removes_its_temporary_file(model, tmp_path, monkeypatch, capsys):
    calls = []
    original = VolumeWriter._store

    def fail_second(self, z, block):
        calls.append(z)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        original(self, z, block)

    monkeypatch.setattr(VolumeWriter, "_store", fail_second)
    out = tmp_path / "decoded.npy"
    assert main(["decode", str(model), "--out", str(out), "--shape", "64,64,2048"]) == 2
    one_line_error(capsys, "No space left")
    assert list(tmp_path.iterdir()) == []


def test_model_file_writes_on_a_full_disk_are_one_line_and_leave_nothing(tmp_path, monkeypatch, capsys):
    data = tmp_path / "v.npy"
    np.save(data, np.random.default_rng(0).random((6, 7, 8), dtype=np.float32))

    def full_disk(self, payload):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(container.Path, "write_bytes", full_disk)
    out = tmp_path / "m.apmgsrn"
    assert main(["train", str(data), "--out", str(out), "--iterations", "2", "--grids", "2", "--resolution", "4"]) == 2
    one_line_error(capsys, "no space left on the device")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.npy"]


def test_outputs_into_a_missing_folder_a_file_as_folder_or_onto_a_folder(model, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for out in (tmp_path / "missing" / "x.npy", blocker / "x.npy", tmp_path):
        assert main(["decode", str(model), "--out", str(out)]) == 2
        one_line_error(capsys)
    plot_targets = (tmp_path / "missing" / "p.png", blocker / "p.png", tmp_path)
    for out in plot_targets:
        assert main(["info", str(model), "--plot", str(out)]) == 2
        one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]
