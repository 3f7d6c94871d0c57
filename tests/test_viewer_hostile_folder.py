"""The viewer survives any file in its folder (issue 11, item 10): symbolic-link loops, named pipes, names
that are not UTF-8, files whose JSON header or preset is nested 100,000 deep. It lists what it can, says
what it left out and why, and opens nothing it did not list. Every hostile file is built on the fly."""

from __future__ import annotations

import json
import os
import shutil
import struct
import threading

import pytest
from viewer_data import make_viewer_folder

from apmgsrn.errors import ApmgsrnError
from apmgsrn.viewer.catalog import MODEL, PRESET, VOLUME, Catalog, CatalogConfig
from apmgsrn.viewer.session import ViewerSession

DEEP_JSON = "[" * 100_000 + "]" * 100_000


def _deep_header_model(path):
    """A safetensors-like file whose JSON header is 100,000 nested lists (200 kB)."""
    header = DEEP_JSON.encode()
    path.write_bytes(struct.pack("<Q", len(header)) + header)
    return path


def _hostile_folder(tmp_path, test_data):
    """The viewer's test folder plus every kind of file the review planted."""
    folder = make_viewer_folder(tmp_path)
    (folder / "loop").symlink_to(folder / "loop")  # a link to itself
    (folder / "ping").symlink_to(folder / "pong")  # two links to each other
    (folder / "pong").symlink_to(folder / "ping")
    (folder / "dangling.npy").symlink_to(folder / "gone.npy")
    (folder / "nested" / "up").symlink_to(folder)  # a folder link back up: walked once, not in circles
    _deep_header_model(folder / "deep_header.weights")  # unknown suffix: its header is read to classify it
    _deep_header_model(folder / "deep_header.apmgsrn")  # listed by suffix; opening it fails in the page
    (folder / "deep.json").write_text(DEEP_JSON, encoding="utf-8")
    os.mkfifo(folder / "pipe.npy")  # reading a named pipe blocks until someone writes to it
    os.mkfifo(folder / "pipe.apmgsrn")
    os.mkfifo(folder / "pipe")
    (folder / "bad\nname.npy").write_bytes((folder / "a_blob.npy").read_bytes())
    with open(os.path.join(os.fsencode(folder), b"latin1_\xe9.npy"), "wb") as raw:  # not UTF-8
        raw.write((folder / "a_blob.npy").read_bytes())
    shutil.copytree(test_data / "reference_bricks", folder / "bricks")
    return folder


def _listing_within(seconds: float, folder, config=CatalogConfig()) -> Catalog:
    """The catalog of a folder, failing (instead of hanging the test run) if listing blocks on a pipe."""
    result = {}
    worker = threading.Thread(target=lambda: result.update(catalog=Catalog(folder, config)), daemon=True)
    worker.start()
    worker.join(seconds)
    assert not worker.is_alive(), "listing the folder blocked (a named pipe was opened?)"
    return result["catalog"]


@pytest.fixture()
def hostile(tmp_path, test_data):
    return _hostile_folder(tmp_path, test_data)


def test_listing_survives_every_hostile_file_and_says_why(hostile):
    catalog = _listing_within(60, hostile)
    entries = {entry.name: entry.kind for entry in catalog.entries()}
    assert entries == {
        "a_blob.npy": VOLUME,
        "bricks": MODEL,
        "broken.apmgsrn": MODEL,
        "deep.json": PRESET,  # listed by suffix; reading it is refused (see the app test)
        "deep_header.apmgsrn": MODEL,
        "link_in.npy": VOLUME,
        "nested/small.npy": VOLUME,
        "reds.json": PRESET,
        "tiny.apmgsrn": MODEL,
    }
    reasons = {skipped.name: skipped.reason for skipped in catalog.skipped}
    for name in ("loop", "ping", "pong", "dangling.npy"):
        assert "link" in reasons[name], name
    assert "outside" in reasons["link_out.npy"]
    for name in ("pipe.npy", "pipe.apmgsrn", "pipe"):
        assert reasons[name] == "not a regular file"
    assert "UTF-8" in reasons[ascii("bad\nname.npy")]  # names shown as Python would spell them
    assert any(name.startswith("'latin1_") and "UTF-8" in reason for name, reason in reasons.items())
    assert "deep_header.weights" not in reasons  # a foreign file: neither listed nor an error


def test_a_hostile_single_path_is_a_user_error(hostile):
    for name in ("pipe.npy", "loop", "dangling.npy"):
        with pytest.raises(ApmgsrnError):
            Catalog(hostile / name)


def test_only_listed_files_open(hostile):
    catalog = Catalog(hostile)
    # Inside the root and of a kind the viewer opens, but not in the listing: refused.
    (hostile / "later.npy").write_bytes((hostile / "a_blob.npy").read_bytes())
    brick = sorted(p.name for p in (hostile / "bricks").glob("*.apmgsrn"))[0]
    for name in ("later.npy", f"bricks/{brick}", "nested/up/a_blob.npy", "pipe.npy", "deep_header.weights"):
        with pytest.raises(ApmgsrnError, match="not a file this viewer lists"):
            catalog.resolve(name)
    # Past the entry limit: what the listing did not reach is not opened either.
    short = Catalog(hostile, CatalogConfig(max_entries=2))
    assert short.truncated and len(short.entries()) == 2
    assert any("stops at 2 entries" in skipped.reason for skipped in short.skipped)
    with pytest.raises(ApmgsrnError, match="not a file this viewer lists"):
        short.resolve("tiny.apmgsrn")
    # A listed file that changed since: a pipe now, or a link out of the folder.
    (hostile / "a_blob.npy").unlink()
    os.mkfifo(hostile / "a_blob.npy")
    with pytest.raises(ApmgsrnError, match="not a regular file"):
        catalog.resolve("a_blob.npy")
    (hostile / "nested" / "small.npy").unlink()
    (hostile / "nested" / "small.npy").symlink_to(hostile.parent / "secret.npy")
    with pytest.raises(ApmgsrnError, match="outside"):
        catalog.resolve("nested/small.npy")
    session = ViewerSession(catalog, "cpu")
    with pytest.raises(ApmgsrnError, match="not a file this viewer lists"):
        session.request_open("later.npy")


def test_presets_nested_too_deeply_are_refused(hostile):
    session = ViewerSession(Catalog(hostile), "cpu")
    with pytest.raises(ApmgsrnError, match="nested too deeply"):
        session.add_presets(hostile / "deep.json", "deep.json")
    assert session.add_presets(hostile / "reds.json", "reds.json") == ["Two Reds (reds.json)"]


def test_the_app_starts_on_a_hostile_folder_and_flags_what_it_left_out(hostile):
    pytest.importorskip("trame", reason="needs the [viewer] extra")
    from apmgsrn.viewer.app import ViewerApp

    app = ViewerApp(_listing_within(60, hostile))
    skipped = {item.name: item.reason for item in app.skipped}
    assert "nested too deeply" in skipped["deep.json"]
    assert "not a regular file" in skipped["pipe.npy"]
    state = app.state
    assert state["skipped_count"] == len(app.skipped)
    assert any(line.startswith("deep.json: ") for line in state["skipped_files"])
    assert "Two Reds (reds.json)" in state["colormaps"]
    assert {entry["value"] for entry in state["entries"]} >= {"a_blob.npy", "tiny.apmgsrn", "bricks"}
    # Opening the model whose header is nested 100,000 deep fails as a message; the view goes on.
    app.session.open_now("a_blob.npy")
    with pytest.raises(ApmgsrnError):
        app.session.open_now("deep_header.apmgsrn")
    assert app.session.source.name == "a_blob.npy"


def test_a_preset_file_of_thousands_of_presets_is_capped(tmp_path):
    from apmgsrn.viewer.settings import ColormapLibrary

    many = [{"Name": f"p{i}", "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1]} for i in range(50)]
    path = tmp_path / "many.json"
    path.write_text(json.dumps(many), encoding="utf-8")
    from apmgsrn.rendering import read_presets

    library = ColormapLibrary(max_choices=40)
    with pytest.raises(ApmgsrnError, match="limit of 40"):
        library.add_presets(read_presets(path), "many.json")
    assert len(library.keys()) < 40  # nothing of the refused file was added
