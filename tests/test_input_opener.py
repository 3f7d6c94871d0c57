"""One opener for every input path (apmgsrn.data.opener): regular files only, links resolved and kept inside
their root, every file a container reaches judged by the same rules, the declared size checked before any
read; and the viewer's folder boundary is that opener. Every hostile input is built on the fly.

A case that would block forever if the rule were missing (a named pipe, /dev/zero) runs in a child process
killed after a deadline, so the suite fails instead of hanging."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from apmgsrn.data import open_volume
from apmgsrn.errors import ApmgsrnError

zarr = pytest.importorskip("zarr")
h5py = pytest.importorskip("h5py")

HUGE = (8192, 8192, 8192)  # 2 TiB as float32: more than half the free memory of any machine this runs on

# Opens a volume (and reads it whole) in a child; prints "refused: MESSAGE" (exit 3) or "opened" (exit 0).
OPEN_SCRIPT = """
import sys
from apmgsrn.data import open_volume
from apmgsrn.errors import ApmgsrnError
try:
    volume = open_volume(sys.argv[1], root=sys.argv[2] or None)
    volume.stats()
except ApmgsrnError as exc:
    print("refused:", exc)
    sys.exit(3)
print("opened")
"""


def isolated(arguments: list[str], deadline: float = 120.0, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run a child Python with ``arguments``; fail the test (never hang it) if the child does not end."""
    try:
        return subprocess.run([sys.executable, *arguments], capture_output=True, text=True, timeout=deadline,
                              cwd=cwd, env={**os.environ, "OMP_NUM_THREADS": "1"})
    except subprocess.TimeoutExpired:
        pytest.fail(f"{arguments[-2:]} did not end within {deadline:.0f} s: a reader blocked or ran on")


def open_isolated(path: Path, root: Path | None = None, cwd: Path | None = None) -> str:
    """``open_volume(path, root=root).stats()`` in a child; returns what it printed (refusals must be one line)."""
    result = isolated(["-c", OPEN_SCRIPT, str(path), str(root or "")], cwd=cwd)
    assert result.returncode in (0, 3), result.stderr[-2000:]
    return result.stdout.strip()


def zarr_store(path: Path, values: np.ndarray | None = None) -> Path:
    """A Zarr (format 3) array of 8^3 float32 in 4^3 chunks, written unless ``values`` is None."""
    array = zarr.create_array(store=str(path), shape=(8, 8, 8), chunks=(4, 4, 4), dtype="f4")
    array[:] = np.arange(512, dtype=np.float32).reshape(8, 8, 8) if values is None else values
    return path


def a_chunk(store: Path) -> Path:
    """One chunk file of a store."""
    chunks = sorted(p for p in store.rglob("*") if p.is_file() and p.name != "zarr.json")
    assert chunks, "the store has no chunk files"
    return chunks[0]


def hdf5_external(path: Path, external: str, shape=(4, 4, 4)) -> Path:
    """An HDF5 file whose one dataset stores its bytes in ``external`` (a name HDF5 resolves itself)."""
    with h5py.File(path, "w") as handle:
        handle.create_dataset("v", shape=shape, dtype="f4", external=[(external, 0, 4 * int(np.prod(shape)))])
    return path


# ------------------------------------------------------------------------------------------ Zarr stores
def test_a_zarr_chunk_that_is_a_named_pipe_is_refused_not_waited_on(tmp_path):
    store = zarr_store(tmp_path / "pipe.zarr")
    chunk = a_chunk(store)
    chunk.unlink()
    os.mkfifo(chunk)
    printed = open_isolated(store)
    assert printed.startswith("refused:") and "named pipe" in printed and chunk.name in printed
    assert printed.count("\n") == 0
    # The command line: one line, exit 2, no model written.
    result = isolated(["-m", "apmgsrn", "train", str(store), "--out", str(tmp_path / "m.apmgsrn"),
                       "--iterations", "2"], deadline=300)
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.startswith("error: ") and result.stderr.count("\n") == 1 and "named pipe" in result.stderr
    assert not (tmp_path / "m.apmgsrn").exists()


def test_a_zarr_chunk_linked_to_dev_zero_is_refused(tmp_path):
    store = zarr_store(tmp_path / "zero.zarr")
    chunk = a_chunk(store)
    chunk.unlink()
    chunk.symlink_to("/dev/zero")
    printed = open_isolated(store)
    assert printed.startswith("refused:") and ("outside" in printed or "character device" in printed)


def test_a_zarr_chunk_linked_outside_the_store_is_refused(tmp_path):
    store = zarr_store(tmp_path / "out.zarr")
    secret = zarr_store(tmp_path / "secret.zarr", np.full((8, 8, 8), 1234.5, dtype=np.float32))
    chunk = a_chunk(store)
    chunk.unlink()
    chunk.symlink_to(a_chunk(secret))  # a real chunk, with another store's values
    with pytest.raises(ApmgsrnError, match="is outside"):
        open_volume(store)
    # A link that stays inside the store is one of its files.
    inner = zarr_store(tmp_path / "inner.zarr")
    first, copy = a_chunk(inner), a_chunk(inner).with_name("copy")
    first.rename(copy)
    first.symlink_to(copy)
    assert open_volume(inner).read().shape == (8, 8, 8)


def test_a_zarr_chunk_swapped_after_the_walk_is_refused_when_read(tmp_path):
    store = zarr_store(tmp_path / "swap.zarr")
    volume = open_volume(store)  # walked: every file regular and inside
    secret = zarr_store(tmp_path / "secret.zarr", np.full((8, 8, 8), 1234.5, dtype=np.float32))
    chunk = a_chunk(store)
    chunk.unlink()
    chunk.symlink_to(a_chunk(secret))
    with pytest.raises(ApmgsrnError, match="is outside"):
        volume.read()


def test_a_zarr_data_file_larger_than_its_array_is_refused(tmp_path):
    store = zarr_store(tmp_path / "sparse.zarr")
    with open(a_chunk(store), "r+b") as handle:
        handle.truncate(4 << 30)  # a sparse 4 GiB chunk of an array of 2 KiB
    with pytest.raises(ApmgsrnError, match="more than its largest array declares"):
        open_volume(store)


# ------------------------------------------------------------------------------------------ HDF5 files
def test_hdf5_external_storage_in_a_named_pipe_is_refused(tmp_path):
    os.mkfifo(tmp_path / "pipe.bin")
    path = hdf5_external(tmp_path / "ext.h5", str(tmp_path / "pipe.bin"))
    printed = open_isolated(path)
    assert printed.startswith("refused:") and "named pipe" in printed and "pipe.bin" in printed


@pytest.mark.parametrize("spelling", ["relative", "absolute"])
def test_hdf5_external_storage_outside_the_root_is_refused(tmp_path, monkeypatch, spelling):
    served = tmp_path / "served"
    served.mkdir()
    np.arange(64, dtype=np.float32).tofile(tmp_path / "secret.bin")
    monkeypatch.chdir(served)  # HDF5 resolves a relative external name against the working folder
    name = "../secret.bin" if spelling == "relative" else str(tmp_path / "secret.bin")
    path = hdf5_external(served / "ext.h5", name)
    with pytest.raises(ApmgsrnError, match="is outside"):
        open_volume(path, root=served)
    # Without a root (the command line on one's own files) external storage in a regular file is read.
    assert open_volume(path).read().reshape(-1).tolist() == list(range(64))


def test_hdf5_external_links_are_refused(tmp_path):
    with h5py.File(tmp_path / "other.h5", "w") as handle:
        handle["v"] = np.ones((4, 4, 4), dtype=np.float32)
    with h5py.File(tmp_path / "linked.h5", "w") as handle:
        handle["own"] = np.zeros((4, 4, 4), dtype=np.float32)
        handle["elsewhere"] = h5py.ExternalLink(str(tmp_path / "other.h5"), "/v")
    for variable in (None, "own", "elsewhere"):
        with pytest.raises(ApmgsrnError, match="link to another file"):
            open_volume(tmp_path / "linked.h5", variable=variable)


def test_a_virtual_dataset_reading_another_file_is_refused(tmp_path):
    with h5py.File(tmp_path / "source.h5", "w") as handle:
        handle["v"] = np.ones((4, 4, 4), dtype=np.float32)
    layout = h5py.VirtualLayout(shape=(4, 4, 4), dtype="f4")
    layout[:] = h5py.VirtualSource(str(tmp_path / "source.h5"), "v", shape=(4, 4, 4))
    with h5py.File(tmp_path / "virtual.h5", "w") as handle:
        handle.create_virtual_dataset("v", layout)
    with pytest.raises(ApmgsrnError, match="virtual dataset"):
        open_volume(tmp_path / "virtual.h5")


# ------------------------------------------------------------------------------------------ declared sizes
def _huge_hdf5(path: Path) -> Path:
    with h5py.File(path, "w") as handle:
        handle.create_dataset("v", shape=HUGE, dtype="f4", chunks=(64, 64, 64), compression="gzip")
    return path


def _huge_netcdf(path: Path) -> Path:
    netCDF4 = pytest.importorskip("netCDF4")
    with netCDF4.Dataset(path, "w") as handle:
        for name, size in zip("zyx", HUGE):
            handle.createDimension(name, size)
        handle.createVariable("v", "f4", ("z", "y", "x"), zlib=True, chunksizes=(64, 64, 64))
    return path


def _huge_zarr(path: Path) -> Path:
    zarr.create_array(store=str(path), shape=HUGE, chunks=(256, 256, 256), dtype="f4")
    return path


def _huge_npy(path: Path) -> Path:
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "<f4", "fortran_order": False, "shape": HUGE})
    return path


@pytest.mark.parametrize("make,name", [(_huge_hdf5, "huge.h5"), (_huge_netcdf, "huge.nc"), (_huge_zarr, "huge.zarr"),
                                       (_huge_npy, "huge.npy")])
def test_a_small_file_declaring_an_8192_cube_is_refused_before_anything_is_read(tmp_path, make, name):
    path = make(tmp_path / name)
    stored = sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size
    assert stored < 1 << 20
    with pytest.raises(ApmgsrnError) as refused:
        open_volume(path)
    assert str(refused.value).startswith(str(path)) and "\n" not in str(refused.value)


def test_a_large_declared_array_that_the_file_really_stores_is_opened_lazily(tmp_path, monkeypatch):
    """The budget rule refuses a claim the file cannot hold, not a volume larger than memory: with a budget
    of 1 KiB, a stored 16^3 float32 volume (16 KiB) still opens, while a sparse one is refused."""
    import apmgsrn.data.opener as opener

    monkeypatch.setattr(opener, "memory_budget", lambda: 1024)
    np.save(tmp_path / "stored.npy", np.ones((16, 16, 16), dtype=np.float32))
    assert open_volume(tmp_path / "stored.npy").shape == (16, 16, 16)
    with h5py.File(tmp_path / "sparse.h5", "w") as handle:
        handle.create_dataset("v", shape=(2048, 2048, 2048), dtype="f4", chunks=(32, 32, 32))
    with pytest.raises(ApmgsrnError, match="declares 2048x2048x2048"):
        open_volume(tmp_path / "sparse.h5")


# ------------------------------------------------------------------------------------------ plain inputs
PIPES_SCRIPT = """
import os, sys
from apmgsrn.data import open_volume
from apmgsrn.errors import ApmgsrnError
for name in sys.argv[1:]:
    try:
        open_volume(name)
        print("opened", name)
    except ApmgsrnError as exc:
        print("refused", exc)
"""


def test_pipes_and_devices_are_refused_under_every_suffix(tmp_path):
    names = []
    for suffix in (".npy", ".h5", ".nc", ".vti", "_4x4x4_uint8.raw"):
        os.mkfifo(tmp_path / f"pipe{suffix}")
        (tmp_path / f"zero{suffix}").symlink_to("/dev/zero")
        names += [str(tmp_path / f"pipe{suffix}"), str(tmp_path / f"zero{suffix}")]
    result = isolated(["-c", PIPES_SCRIPT, *names])
    lines = result.stdout.strip().splitlines()
    assert len(lines) == len(names) and all(line.startswith("refused") for line in lines), result.stdout


PVD_SCRIPT = """
import sys
from apmgsrn.errors import ApmgsrnError
from apmgsrn.series.data import open_series
try:
    open_series(sys.argv[1])
    print("opened")
except ApmgsrnError as exc:
    print("refused:", exc)
"""


def test_a_pvd_that_is_a_pipe_or_lists_a_pipe_is_refused(tmp_path):
    os.mkfifo(tmp_path / "pipe.pvd")
    assert "named pipe" in isolated(["-c", PVD_SCRIPT, str(tmp_path / "pipe.pvd")]).stdout
    np.save(tmp_path / "a.npy", np.ones((4, 4, 4), dtype=np.float32))
    os.mkfifo(tmp_path / "b.npy")
    (tmp_path / "series.pvd").write_text(
        '<VTKFile type="Collection"><Collection><DataSet timestep="0" file="a.npy"/>'
        '<DataSet timestep="1" file="b.npy"/></Collection></VTKFile>'
    )
    printed = isolated(["-c", PVD_SCRIPT, str(tmp_path / "series.pvd")]).stdout
    assert printed.startswith("refused:") and "b.npy" in printed and "named pipe" in printed


# ------------------------------------------------------------------------------------------ the viewer
def _served_folder(tmp_path: Path) -> Path:
    """A served folder holding a plain volume and, beside it, every container that reaches outside."""
    served = tmp_path / "served"
    served.mkdir()
    np.save(served / "plain.npy", np.linspace(0, 1, 512, dtype=np.float32).reshape(8, 8, 8))
    secret = zarr_store(tmp_path / "secret.zarr", np.full((8, 8, 8), 1234.5, dtype=np.float32))
    zarr_store(served / "good.zarr")
    out = zarr_store(served / "out.zarr")
    chunk = a_chunk(out)
    chunk.unlink()
    chunk.symlink_to(a_chunk(secret))
    zero = zarr_store(served / "zero.zarr")
    chunk = a_chunk(zero)
    chunk.unlink()
    chunk.symlink_to("/dev/zero")
    np.full(64, 1234.5, dtype=np.float32).tofile(tmp_path / "secret.bin")
    hdf5_external(served / "absolute.h5", str(tmp_path / "secret.bin"))
    with h5py.File(served / "linked.h5", "w") as handle:
        handle["v"] = h5py.ExternalLink(str(tmp_path / "other.h5"), "/v")
    with h5py.File(tmp_path / "other.h5", "w") as handle:
        handle["v"] = np.full((4, 4, 4), 1234.5, dtype=np.float32)
    return served


def test_the_catalogue_lists_only_what_the_opener_accepts_under_the_folder(tmp_path):
    from apmgsrn.viewer.catalog import Catalog

    served = _served_folder(tmp_path)
    catalog = Catalog(served)
    assert [entry.name for entry in catalog.entries()] == ["good.zarr", "plain.npy"]
    reasons = {skipped.name: skipped.reason for skipped in catalog.skipped}
    assert "outside" in reasons["out.zarr"] and "outside" in reasons["zero.zarr"]
    assert "outside" in reasons["absolute.h5"] and "link to another file" in reasons["linked.h5"]
    # A listed store changed since: a chunk now links out of the folder; the page's request is refused.
    chunk = a_chunk(served / "good.zarr")
    chunk.unlink()
    chunk.symlink_to(a_chunk(tmp_path / "secret.zarr"))
    with pytest.raises(ApmgsrnError, match="refused .good.zarr.*outside"):
        catalog.resolve("good.zarr")


VIEWER_SCRIPT = """
import json, sys
from pathlib import Path
from apmgsrn.viewer.catalog import Catalog
from apmgsrn.viewer.session import ViewerSession
from apmgsrn.viewer.settings import ViewerConfig

served = Path(sys.argv[1])
messages = []
config = ViewerConfig(image_width=16, image_height=16, samples_per_ray=8, batch_size=1024, chunk_pixels=64)
session = ViewerSession(Catalog(served), "cpu", config, on_message=lambda kind, text: messages.append((kind, text)))
store = served / "late.zarr"
for chunk in sorted(p for p in store.rglob("*") if p.is_file() and p.name != "zarr.json")[:1]:
    chunk.unlink()
    chunk.symlink_to(sys.argv[2])  # after the listing: the store now reaches sys.argv[2]
try:
    session.request_open("late.zarr")  # refused at once when the catalogue sees the change
except Exception as exc:
    messages.append(("error", str(exc)))
session.run_until_idle()
errors = [text for kind, text in messages if kind == "error"]
shown = session.source.name if session.source else None
session.request_open("plain.npy")
session.run_until_idle()
print(json.dumps({"errors": errors, "shown_after_refusal": shown, "shown": session.source.name,
                  "range": list(session.source.value_range)}))
"""


@pytest.mark.parametrize("target", ["secret chunk", "/dev/zero"])
def test_the_viewer_refuses_a_store_reaching_outside_and_then_opens_a_plain_volume(tmp_path, target):
    served = _served_folder(tmp_path)
    zarr_store(served / "late.zarr")
    reached = str(a_chunk(tmp_path / "secret.zarr")) if target == "secret chunk" else "/dev/zero"
    result = isolated(["-c", VIEWER_SCRIPT, str(served), reached], deadline=300)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["errors"] and "late.zarr" in report["errors"][-1]
    assert report["shown_after_refusal"] is None
    assert report["shown"] == "plain.npy" and report["range"] == [0.0, 1.0]  # never 1234.5, the outside value


def test_the_viewer_opens_volumes_with_its_folder_as_the_readers_root(tmp_path, monkeypatch):
    """What the catalogue checks, the reader checks again when it opens: the session hands the served
    folder to ``open_volume`` as its root."""
    import apmgsrn.viewer.session as session_module
    from apmgsrn.viewer.catalog import Catalog

    served = _served_folder(tmp_path)
    seen = {}

    def record(path, device, options, name):
        seen.update(path=path, volume=options.volume)
        raise ApmgsrnError("stop here")

    monkeypatch.setattr(session_module, "open_source", record)
    session = session_module.ViewerSession(Catalog(served), "cpu")
    with pytest.raises(ApmgsrnError, match="stop here"):
        session.open_now("plain.npy")
    assert seen["volume"]["root"] == served.resolve() and seen["path"] == (served / "plain.npy").resolve()
    # and the reader refuses, under that root, what reaches outside it
    with pytest.raises(ApmgsrnError, match="is outside"):
        open_volume(served / "absolute.h5", root=served)
