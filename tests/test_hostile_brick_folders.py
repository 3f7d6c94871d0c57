"""Hostile and malformed brick-model folders, built on the fly from the committed reference folder: each
is refused with one ApmgsrnError line (the CLI's exit 2) before any brick is built, and an unfinished
folder says truthfully what is missing."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io.container import sealed_manifest_text

REFERENCE = Path(__file__).parent / "data" / "reference_bricks"


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    out = tmp_path / "bricks"
    shutil.copytree(REFERENCE, out)
    return out


def edit_manifest(folder: Path, change) -> None:
    path = folder / "manifest.json"
    manifest = json.loads(path.read_text())
    change(manifest)
    path.write_text(sealed_manifest_text(manifest))


def set_brick(key: str, value):
    def change(manifest: dict) -> None:
        manifest["bricks"][0][key] = value
    return change


MALFORMED = {
    "a brick without a name": set_brick("name", None),
    "a brick summary that is a string": set_brick("summary", "fine"),
    "a brick file outside the folder": set_brick("file", "../elsewhere.apmgsrn"),
    "a brick box that is not three numbers": set_brick("stop", [24, "x", 14]),
    "bricks that are not a list": lambda m: m.update(bricks={"0": "brick"}),
    "a grid of zero bricks": lambda m: m.update(grid=[0, 1, 1]),
    "a negative volume shape": lambda m: m.update(volume_shape=[-48, 64, 80]),
    "complete given as a string": lambda m: m.update(complete="yes"),
}


@pytest.mark.parametrize("case", list(MALFORMED), ids=list(MALFORMED))
def test_malformed_manifests_are_one_line_errors(folder: Path, case: str, capsys) -> None:
    edit_manifest(folder, MALFORMED[case])
    with pytest.raises(ApmgsrnError) as caught:
        apmgsrn.load(folder)
    assert "\n" not in str(caught.value) and "manifest" in str(caught.value)
    assert main(["info", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and "Traceback" not in err


def test_a_manifest_claiming_a_million_bricks_is_refused_at_once(folder: Path) -> None:
    def million(manifest: dict) -> None:
        manifest["grid"] = [100, 100, 100]
        manifest["bricks"] = [{}] * 10**6
    edit_manifest(folder, million)
    start = time.perf_counter()
    with pytest.raises(ApmgsrnError, match="manifest"):
        apmgsrn.load(folder)
    # Refused from the counts, not after planning or opening a million bricks (a generous bound for a
    # busy machine: planning them would take minutes).
    assert time.perf_counter() - start < 30


def test_deeply_nested_manifest_json_is_refused(folder: Path) -> None:
    (folder / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ApmgsrnError, match="manifest"):
        apmgsrn.load(folder)


def test_an_unfinished_folder_with_every_brick_says_the_run_ended_early(folder: Path) -> None:
    edit_manifest(folder, lambda m: m.update(complete=False))
    with pytest.raises(ApmgsrnError) as caught:
        apmgsrn.load(folder)
    message = str(caught.value)
    assert "unfinished" in message and "before it finished the manifest" in message
    assert "0 of" not in message and "none" not in message


def test_an_unfinished_folder_names_its_missing_bricks(folder: Path) -> None:
    edit_manifest(folder, lambda m: m.update(complete=False))
    (folder / "brick_001_000_000.apmgsrn").unlink()
    with pytest.raises(ApmgsrnError, match=r"1 of 2 bricks missing: brick_001_000_000"):
        apmgsrn.load(folder)


def test_a_brick_file_that_is_a_symlink_is_refused(folder: Path, tmp_path: Path) -> None:
    target = tmp_path / "outside.apmgsrn"
    shutil.move(folder / "brick_000_000_000.apmgsrn", target)
    (folder / "brick_000_000_000.apmgsrn").symlink_to(target)
    with pytest.raises(ApmgsrnError, match="brick_000_000_000"):
        apmgsrn.load(folder)


def test_the_untouched_copy_loads(folder: Path) -> None:
    model = apmgsrn.load(folder)
    assert model.description.bricks is not None and len(model.description.bricks.entries) == 2
