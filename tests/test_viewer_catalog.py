"""The viewer's catalog: what under PATH is listed, and every way out of PATH refused."""

from __future__ import annotations

import pytest
from viewer_data import make_viewer_folder

from apmgsrn.errors import ApmgsrnError
from apmgsrn.viewer.catalog import MODEL, PRESET, VOLUME, Catalog, CatalogConfig


@pytest.fixture()
def folder(tmp_path):
    return make_viewer_folder(tmp_path)


def test_lists_models_volumes_and_presets_under_the_folder(folder):
    entries = {entry.name: entry.kind for entry in Catalog(folder).entries()}
    assert entries == {
        "a_blob.npy": VOLUME,
        "broken.apmgsrn": MODEL,  # listed by its suffix; opening it fails in the page, not here
        "link_in.npy": VOLUME,  # a link that stays inside is fine
        "nested/small.npy": VOLUME,
        "reds.json": PRESET,
        "tiny.apmgsrn": MODEL,
    }
    # Not listed: notes.txt (no data), .hidden.npy (hidden), link_out.npy (leads outside).


def test_depth_limit_stops_the_walk(folder):
    names = [entry.name for entry in Catalog(folder, CatalogConfig(max_depth=1)).entries()]
    assert "nested/small.npy" not in names and "a_blob.npy" in names
    with pytest.raises(ApmgsrnError, match="deeper"):
        Catalog(folder, CatalogConfig(max_depth=1)).resolve("nested/small.npy")


def test_model_under_another_suffix_is_recognised_by_its_header(folder):
    (folder / "tiny.apmgsrn").rename(folder / "renamed.bin.model")
    entries = {entry.name: entry.kind for entry in Catalog(folder).entries()}
    assert entries["renamed.bin.model"] == MODEL


@pytest.mark.parametrize(
    "name",
    [
        "../secret.npy",
        "nested/../../secret.npy",
        "/etc/passwd",
        "link_out.npy",  # a symbolic link out of the folder
        "~/secret.npy",
        "",
        "a\\..\\..\\secret.npy",
        ".hidden.npy",
        "notes.txt",  # inside, but not something the viewer opens
        "missing.npy",
    ],
)
def test_names_outside_or_unlisted_are_refused(folder, name):
    with pytest.raises(ApmgsrnError):
        Catalog(folder).resolve(name)


def test_resolve_returns_the_file_inside_and_checks_the_kind(folder):
    catalog = Catalog(folder)
    assert catalog.resolve("nested/small.npy") == (folder / "nested" / "small.npy").resolve()
    assert catalog.resolve("tiny.apmgsrn", kinds=(MODEL,)).name == "tiny.apmgsrn"
    with pytest.raises(ApmgsrnError, match="not a model or volume"):
        catalog.resolve("reds.json", kinds=(MODEL, VOLUME))


def test_a_single_file_serves_only_itself(folder):
    catalog = Catalog(folder / "tiny.apmgsrn")
    assert [(e.name, e.kind) for e in catalog.entries()] == [("tiny.apmgsrn", MODEL)]
    assert catalog.resolve("tiny.apmgsrn").name == "tiny.apmgsrn"
    with pytest.raises(ApmgsrnError, match="serves tiny.apmgsrn only"):
        catalog.resolve("a_blob.npy")


def test_missing_or_foreign_path_is_a_user_error(folder):
    with pytest.raises(ApmgsrnError, match="no such file"):
        Catalog(folder / "nope")
    with pytest.raises(ApmgsrnError, match="neither a model"):
        Catalog(folder / "notes.txt")
