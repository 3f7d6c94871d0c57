"""Every model file detects its own damage: single bit flips anywhere in a float32, packed, series, packed series
or brick file (header JSON included) are refused on load or change no decoded value; a brick folder refuses a
brick swapped with another or taken from another run; files written before checksums load with a note;
``apmgsrn verify`` checks files, checkpoints and folders without evaluating them (exit 0 / 2)."""

from __future__ import annotations

import json
import random
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.data import open_volume
from apmgsrn.decomposition.coordinator import train_bricks
from apmgsrn.decomposition.executor import LocalJobQueue
from apmgsrn.decomposition.planner import DecompositionConfig
from apmgsrn.errors import ApmgsrnError, ApmgsrnNote
from apmgsrn.io import container, verify_file
from apmgsrn.io.brick_folder import manifest_path
from apmgsrn.io.container import manifest_checksum, sealed_manifest_text
from apmgsrn.io.description import time_steps
from apmgsrn.models.registry import preset_config
from apmgsrn.training.checkpoint import CHECKPOINT_KIND
from apmgsrn.training.trainer import TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = ["--model", "apmgsrn", "--grids", "2", "--resolution", "8", "--width", "16", "--iterations", "20",
        "--batch-size", "1024", "--device", "cpu"]
#: Random bit flips per file, and more inside its header JSON (where the description and tensor table are).
FLIPS, HEADER_FLIPS = 64, 32
POINTS = torch.cat([torch.rand(300, 3, generator=torch.Generator().manual_seed(5)) * 2 - 1,
                    torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])])


@pytest.fixture(scope="module")
def models(test_data, tmp_path_factory) -> dict[str, Path]:
    """A model file of each kind, trained for a few iterations on the real volumes of tests/data."""
    folder = tmp_path_factory.mktemp("kinds")
    volume = str(test_data / "neghip_32x32x32_uint8.npy")
    series = str(test_data / "viscous_fingers_run01" / "*.vti")
    paths = {kind: folder / f"{kind}.apmgsrn" for kind in ("field", "packed-field", "series", "packed-series")}
    assert main(["train", volume, "--out", str(paths["field"]), *TINY]) == 0
    assert main(["pack", str(paths["field"]), volume, "--bits", "8", "--qat-iterations", "0",
                 "--out", str(paths["packed-field"])]) == 0
    assert main(["train", series, "--out", str(paths["series"]), "--series-training", "joint", "--basis", "2",
                 *TINY]) == 0
    assert main(["pack", str(paths["series"]), series, "--bits", "8", "--qat-iterations", "0",
                 "--decoder-iterations", "0", "--out", str(paths["packed-series"])]) == 0
    for kind, path in paths.items():
        assert container.read_header(path).kind == kind
    return paths


def train_folder(test_data, out: Path) -> Path:
    """A two-brick model of the 24^3 neghip crop, a few iterations per brick."""
    train = TrainConfig(iterations=20, batch_size=1024, seed=0)
    queue = LocalJobQueue(workers=1, retries=0)
    queue.threads_per_job = 1
    with queue:
        summary = train_bricks(open_volume(test_data / "reference_neghip_24.npy"),
                               DecompositionConfig((2, 1, 1), ghost_cells=1),
                               preset_config("apmgsrn", "small", grids=2, resolution=(8, 8, 8), width=16), train,
                               out, queue, device="cpu")
    assert summary.complete
    return out


@pytest.fixture(scope="module")
def bricks(test_data, tmp_path_factory) -> Path:
    return train_folder(test_data, tmp_path_factory.mktemp("bricks") / "model")


def decoded(path: Path) -> list[torch.Tensor]:
    """The values a model gives at the fixed points, every time step."""
    model = apmgsrn.load(path)
    with torch.no_grad():
        return [model.step_field(t)(POINTS) for t in range(time_steps(model.description))]


def flip_positions(data: bytes, seed: int) -> list[int]:
    """Bit positions: random over the file, and random inside its header JSON."""
    rng = random.Random(seed)
    header_end = 8 + int.from_bytes(data[:8], "little")
    return ([rng.randrange(len(data) * 8) for _ in range(FLIPS)]
            + [rng.randrange(8 * 8, header_end * 8) for _ in range(HEADER_FLIPS)])


def flipped(data: bytes, bit: int) -> bytes:
    damaged = bytearray(data)
    damaged[bit // 8] ^= 1 << (bit % 8)
    return bytes(damaged)


def assert_flips_are_caught(target: Path, load_path: Path, original: list[torch.Tensor], positions: list[int]):
    """Each flip of ``target`` makes loading ``load_path`` fail with ApmgsrnError, or decode the same values.

    Returns:
        How many flips were refused.
    """
    data = target.read_bytes()
    refused = 0
    for bit in positions:
        target.write_bytes(flipped(data, bit))
        try:
            values = decoded(load_path)
        except ApmgsrnError as exc:
            assert "\n" not in str(exc)
            refused += 1
            continue
        finally:
            target.write_bytes(data)
        assert len(values) == len(original), bit
        for a, b in zip(values, original):
            assert torch.equal(a, b), f"bit {bit} of {target.name} changed decoded values silently"
    return refused


@pytest.mark.parametrize("kind", ["field", "packed-field", "series", "packed-series"])
def test_single_bit_flips_in_every_kind_of_file_are_refused_or_harmless(models, kind, tmp_path):
    path = tmp_path / "m.apmgsrn"
    shutil.copyfile(models[kind], path)
    original = decoded(path)
    positions = flip_positions(path.read_bytes(), seed=len(kind))
    refused = assert_flips_are_caught(path, path, original, positions)
    assert refused >= len(positions) // 2  # nearly every byte of a file is a checksummed byte


def test_single_bit_flips_in_a_brick_folder_are_refused_or_harmless(bricks, tmp_path):
    folder = tmp_path / "bricks"
    shutil.copytree(bricks, folder)
    original = decoded(folder)
    for number, brick in enumerate(sorted(folder.glob("brick_*.apmgsrn"))):
        assert_flips_are_caught(brick, folder, original, flip_positions(brick.read_bytes(), seed=number))
    manifest = manifest_path(folder)
    rng = random.Random(7)
    positions = [rng.randrange(manifest.stat().st_size * 8) for _ in range(FLIPS)]
    assert_flips_are_caught(manifest, folder, original, positions)


def test_a_damaged_tensor_is_named(models, tmp_path):
    path = tmp_path / "m.apmgsrn"
    data = models["field"].read_bytes()
    path.write_bytes(flipped(data, (len(data) - 3) * 8))  # inside the last tensor's bytes
    with pytest.raises(ApmgsrnError, match=r"m.apmgsrn: damaged: checksum of tensor '.+' does not match"):
        apmgsrn.load(path)
    header = container.read_header(path)  # the header is intact: only the bytes are refused
    assert header.checksums is not None and header.digest


def _rewritten(source: Path, out: Path, change) -> Path:
    """``source`` written again by plain safetensors with its metadata passed through ``change``."""
    with open(source, "rb") as f:
        meta = json.loads(f.read(int.from_bytes(f.read(8), "little")))["__metadata__"]
    change(meta)
    save_file(load_file(str(source)), str(out), metadata=meta)
    return out


def _as_version(version: str):
    def change(meta: dict) -> None:
        meta.pop("checksums")
        meta["format_version"] = version
    return change


def test_a_file_of_format_2_without_checksums_loads_with_one_note(models, tmp_path):
    for kind in ("field", "packed-field"):
        old = _rewritten(models[kind], tmp_path / f"old-{kind}.apmgsrn", _as_version("2"))
        with pytest.warns(ApmgsrnNote, match="old-.*model format 2, written before checksums") as notes:
            values = decoded(old)
            decoded(old)  # once per file
        assert len([n for n in notes if issubclass(n.category, ApmgsrnNote)]) == 1
        assert all(torch.equal(a, b) for a, b in zip(values, decoded(models[kind])))
        assert apmgsrn.load(old).description.format_version == 2


@pytest.mark.parametrize("version", ["3", "0", "-1"])
def test_a_file_without_checksums_of_format_3_or_of_no_format_is_refused(models, tmp_path, version):
    hostile = _rewritten(models["field"], tmp_path / "h.apmgsrn", _as_version(version))
    expected = "checksums .* are missing" if version == "3" else f"model format {version} does not exist"
    with pytest.raises(ApmgsrnError, match=expected):
        apmgsrn.load(hostile)


def test_checksums_are_verified_even_where_the_version_says_there_are_none(models, tmp_path):
    """A flip that turns version 3 into 2 leaves the checksums there; they are checked, and cover the version."""
    hostile = _rewritten(models["field"], tmp_path / "h.apmgsrn", lambda meta: meta.update(format_version="2"))
    with pytest.raises(ApmgsrnError, match="damaged: checksum of the description"):
        container.read_header(hostile)


def _swap(folder: Path, a: str, b: str) -> None:
    (folder / a).rename(folder / "tmp")
    (folder / b).rename(folder / a)
    (folder / "tmp").rename(folder / b)


def test_swapped_bricks_are_refused_naming_the_brick(bricks, tmp_path):
    folder = tmp_path / "swapped"
    shutil.copytree(bricks, folder)
    _swap(folder, "brick_000_000_000.apmgsrn", "brick_001_000_000.apmgsrn")
    with pytest.raises(ApmgsrnError, match="brick_000_000_000.apmgsrn: not the model of brick_000_000_000"):
        apmgsrn.load(folder)


def test_a_brick_from_another_run_is_refused(bricks, test_data, tmp_path):
    other = train_folder(test_data, tmp_path / "other")
    folder = tmp_path / "mixed"
    shutil.copytree(bricks, folder)
    shutil.copyfile(other / "brick_001_000_000.apmgsrn", folder / "brick_001_000_000.apmgsrn")
    with pytest.raises(ApmgsrnError, match="brick_001_000_000.apmgsrn: the model of brick_001_000_000 from another "
                                           "training run"):
        apmgsrn.load(folder)
    assert json.loads(manifest_path(other).read_text())["run_id"] != json.loads(
        manifest_path(bricks).read_text())["run_id"]


def test_a_brick_replaced_by_a_consistent_file_of_other_bytes_is_refused(bricks, tmp_path):
    """A brick written again (checksums made anew, same brick and run) is not the file the manifest recorded."""
    folder = tmp_path / "replaced"
    shutil.copytree(bricks, folder)
    brick = folder / "brick_000_000_000.apmgsrn"
    with open(brick, "rb") as f:
        meta = json.loads(f.read(int.from_bytes(f.read(8), "little")))["__metadata__"]
    tensors = load_file(str(brick))
    tensors["decoder.4.weight"] = tensors["decoder.4.weight"] * 1.5
    brick.write_bytes(container.sealed_file_bytes(tensors, meta))
    with pytest.raises(ApmgsrnError, match="brick_000_000_000.apmgsrn: damaged: checksum of the brick file of "
                                           "brick_000_000_000 does not match the manifest's"):
        apmgsrn.load(folder)


def test_a_manifest_of_format_2_loads_with_a_note(bricks, tmp_path):
    folder = tmp_path / "old"
    shutil.copytree(bricks, folder)
    manifest = json.loads(manifest_path(folder).read_text())
    manifest["format_version"] = 2
    del manifest["run_id"]
    for entry in manifest["bricks"]:
        del entry["checksum"], entry["run"]
    del manifest["manifest_checksum"]  # written before manifests carried one
    manifest_path(folder).write_text(json.dumps(manifest))
    with pytest.warns(ApmgsrnNote, match="manifest.json: brick manifest of format 2"):
        values = decoded(folder)
    assert all(torch.equal(a, b) for a, b in zip(values, decoded(bricks)))


def test_a_manifest_of_format_3_without_its_records_is_refused(bricks, tmp_path):
    folder = tmp_path / "stripped"
    shutil.copytree(bricks, folder)
    manifest = json.loads(manifest_path(folder).read_text())
    del manifest["bricks"][1]["checksum"]
    manifest_path(folder).write_text(sealed_manifest_text(manifest))
    with pytest.raises(ApmgsrnError, match=r"bricks\[1\] records no checksum"):
        apmgsrn.load(folder)


def test_a_manifest_changed_after_it_was_written_is_refused_as_damaged(bricks, tmp_path):
    """A brick folder's manifest carries a crc32c of its own content: a number changed in it that every field
    check accepts (the value range) is refused as damage, in one line and with exit code 2 from the command
    line; the same content sealed again loads."""
    folder = tmp_path / "changed"
    shutil.copytree(bricks, folder)
    manifest = json.loads(manifest_path(folder).read_text())
    assert manifest["manifest_checksum"] == manifest_checksum(manifest)
    low, high = manifest["value_range"]
    manifest["value_range"] = [low, high + (high - low)]
    manifest_path(folder).write_text(json.dumps(manifest, indent=1))
    with pytest.raises(ApmgsrnError, match="manifest.json: damaged: the brick model manifest's checksum") as caught:
        apmgsrn.load(folder)
    assert "\n" not in str(caught.value)
    assert main(["info", str(folder)]) == 2
    manifest_path(folder).write_text(sealed_manifest_text(manifest))
    apmgsrn.load(folder)


def test_a_manifest_written_without_its_own_checksum_loads_with_a_note(bricks, tmp_path):
    folder = tmp_path / "unsealed"
    shutil.copytree(bricks, folder)
    manifest = json.loads(manifest_path(folder).read_text())
    del manifest["manifest_checksum"]
    manifest_path(folder).write_text(json.dumps(manifest, indent=1))
    with pytest.warns(ApmgsrnNote, match="manifest.json: brick model manifest written without its own checksum"):
        values = decoded(folder)
    assert all(torch.equal(a, b) for a, b in zip(values, decoded(bricks)))


# ------------------------------------------------------------------------------------------- verify
def test_verify_passes_every_good_kind_and_a_checkpoint(models, bricks, tmp_path, capsys):
    checkpoint = tmp_path / "m.apmgsrn.ckpt"
    container.save_tensors(checkpoint, {"w": torch.arange(6.0)}, CHECKPOINT_KIND, {"state": {"iteration": 3}})
    assert main(["verify", *map(str, models.values()), str(bricks), str(checkpoint)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    # One line per file: four model files, the manifest, two bricks, the folder as a whole, the checkpoint.
    assert len(lines) == 9 and all(": ok (" in line for line in lines)
    assert "training-state, checksums only" in lines[-1]
    assert verify_file(models["field"]).kind == "field"
    assert all(check.ok for check in apmgsrn.verify(bricks))


def test_verify_fails_with_exit_2_naming_each_damaged_file(models, bricks, tmp_path, capsys):
    damaged = tmp_path / "d.apmgsrn"
    data = models["packed-series"].read_bytes()
    damaged.write_bytes(flipped(data, (len(data) - 5) * 8))
    folder = tmp_path / "swapped"
    shutil.copytree(bricks, folder)
    _swap(folder, "brick_000_000_000.apmgsrn", "brick_001_000_000.apmgsrn")
    assert main(["verify", str(models["field"]), str(damaged), str(folder)]) == 2
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].endswith(": ok (field)")
    assert lines[1] == f"{damaged}: damaged: checksum of tensor 'payload' does not match (the file was changed " \
                       "after it was written)"
    assert lines[2].endswith("manifest.json: ok (brick manifest)")
    assert "brick_000_000_000.apmgsrn: not the model of brick_000_000_000" in lines[3]
    assert "brick_001_000_000.apmgsrn: not the model of brick_001_000_000" in lines[4]
    assert len(lines) == 5  # the folder as a whole is opened only when every file is good


def test_verify_of_old_files_says_they_carry_no_checksums(test_data, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("error", ApmgsrnNote)  # the report says it; no separate note
        assert main(["verify", str(test_data / "reference_field.apmgsrn")]) == 0
    assert "written before checksums, damage cannot be detected" in capsys.readouterr().out


def test_verify_of_what_is_not_a_model_exits_2(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "v.npy").write_bytes(np.zeros(8, np.float32).tobytes())
    assert main(["verify", str(tmp_path / "empty"), str(tmp_path / "v.npy"), str(tmp_path / "missing")]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 3 and "not a model folder" in out[0] and "not an apmgsrn model file" in out[1]
    assert "no such model file" in out[2]


def test_verify_checks_a_time_series_brick_folder_group_by_group(test_data, tmp_path, capsys):
    from apmgsrn.series.bricks import train_series_bricks
    from apmgsrn.series.data import open_series
    from apmgsrn.series.field import SeriesConfig, SeriesFieldConfig

    series = open_series(str(test_data / "viscous_fingers_run01" / "*.vti")).absolute()
    config = SeriesFieldConfig(preset_config("apmgsrn", "small", grids=2, resolution=(8, 8, 8), width=16),
                               SeriesConfig(4, 2, "learned"))
    queue = LocalJobQueue(workers=1, retries=0)
    queue.threads_per_job = 1
    out = tmp_path / "series_bricks"
    with queue:
        summary = train_series_bricks(series, DecompositionConfig((2, 1, 1), ghost_cells=1), config,
                                      TrainConfig(iterations=10, batch_size=1024), out, queue, group_steps=2)
    assert summary.complete
    assert main(["verify", str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    # Two step groups, each a manifest and two bricks, then the series as a whole.
    assert len(lines) == 7 and all(": ok (" in line for line in lines) and "series-bricks model" in lines[-1]
    brick = out / "steps_000002_000004" / "brick_001_000_000.apmgsrn"
    data = brick.read_bytes()
    brick.write_bytes(flipped(data, (len(data) - 2) * 8))
    assert main(["verify", str(out)]) == 2
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 6 and lines[-1].startswith(f"{brick}: damaged: checksum of tensor")
    brick.write_bytes(data)
    # The series' own manifest is sealed too: a step renamed after it was written is damage.
    series_json = out / "series.json"
    record = json.loads(series_json.read_text())
    record["steps"][0]["label"] -= 0.25  # still a number before the next step's: every field check accepts it
    series_json.write_text(json.dumps(record, indent=1))
    with pytest.raises(ApmgsrnError, match="series.json: damaged: the time-series brick manifest's checksum"):
        apmgsrn.load(out)
    series_json.write_text(sealed_manifest_text(record))  # the same content sealed again loads
    apmgsrn.load(out)


def test_the_command_line_prints_the_note_as_one_line(models, tmp_path):
    import subprocess
    import sys

    old = _rewritten(models["field"], tmp_path / "old.apmgsrn", _as_version("2"))
    done = subprocess.run([sys.executable, "-m", "apmgsrn", "info", str(old)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0
    assert done.stderr.strip().splitlines() == [f"note: {old}: model format 2, written before checksums: damage to "
                                                "it cannot be detected"]
