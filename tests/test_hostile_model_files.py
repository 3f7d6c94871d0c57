"""Hostile and malformed model files, built on the fly: each is refused with one ApmgsrnError line (the
CLI's exit 2) before anything is built from it, or loads correctly where that is the right answer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SourceInfo, save_field
from apmgsrn.io.container import FORMAT, FORMAT_VERSION
from apmgsrn.models import field as field_module
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config


@pytest.fixture()
def good_model(tmp_path) -> Path:
    torch.manual_seed(0)
    field = NeuralField(preset_config("apmgsrn", "small", grids=2, resolution=(4, 4, 4), width=8),
                        value_min=0.0, value_max=2.0, fit_min=0.0, fit_max=2.0, volume_shape=(6, 7, 8))
    path = tmp_path / "good.apmgsrn"
    save_field(path, field, SourceInfo(path="v.npy"), {"iterations": 3, "history": {"iteration": [0]}})
    return path


def rewrite(path: Path, out: Path, description=None, raw_description: str | None = None, tensors=None) -> Path:
    """A copy of ``path`` with its description (or raw description text, or tensors) replaced."""
    with open(path, "rb") as f:
        length = int.from_bytes(f.read(8), "little")
        meta = json.loads(f.read(length))["__metadata__"]
    current = json.loads(meta["description"])
    if description is not None:
        description(current)  # mutates in place
    meta["description"] = raw_description if raw_description is not None else json.dumps(current)
    stored = load_file(str(path))
    if tensors is not None:
        tensors(stored)  # mutates in place
    save_file(stored, str(out), metadata=meta)
    return out


def set_path(keys: list, value):
    def mutate(d):
        target = d
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value
    return mutate


@pytest.fixture()
def no_module_built(monkeypatch):
    """Fail the test if the loader builds a field (refusals must come before any allocation)."""
    def refuse(*args, **kwargs):
        raise AssertionError("a module was built from a file that should have been refused first")
    monkeypatch.setattr(field_module.NeuralField, "__init__", refuse)


SIZE_CLAIMS = {
    "resolution 300^3": ["field", "encoder", "resolution"], "100,000 grids": ["field", "encoder", "grids"],
    "width 30,000": ["field", "decoder", "width"], "hidden layers 10^6": ["field", "decoder", "hidden_layers"],
}
SIZE_VALUES = {"resolution 300^3": [300, 300, 300], "100,000 grids": 100_000, "width 30,000": 30_000,
               "hidden layers 10^6": 1_000_000}


@pytest.mark.parametrize("claim", sorted(SIZE_CLAIMS))
def test_size_claims_beyond_the_stored_tensors_are_refused_before_allocating(good_model, tmp_path, claim,
                                                                            no_module_built):
    hostile = rewrite(good_model, tmp_path / "h.apmgsrn", set_path(SIZE_CLAIMS[claim], SIZE_VALUES[claim]))
    with pytest.raises(ApmgsrnError, match="model file is inconsistent"):
        apmgsrn.load(hostile)


MALFORMED = {
    "encoder a list": (["field", "encoder"], [1, 2]),
    "encoder a string": (["field", "encoder"], "grids"),
    "unknown encoder field": (["field", "encoder", "evil"], 1),
    "grids a string": (["field", "encoder", "grids"], "16"),
    "source a list": (["source"], [1]),
    "source path a number": (["source", "path"], 3),
    "training a string": (["training"], "fast"),
    "history a string": (["training", "history"], "x"),
    "history of strings": (["training", "history", "iteration"], ["a"]),
    "volume shape of two": (["volume_shape"], [4, 4]),
    "volume shape zeros": (["volume_shape"], [0, 0, 0]),
    "volume shape negative": (["volume_shape"], [-4, 4, 4]),
    "offset a string": (["transform", "offset"], "1"),
    "transform kind unknown": (["transform", "kind"], "exec"),
    "value range NaN": (["value_min"], float("nan")),
    "min above max": (["value_min"], 5.0),
    "model kind unknown": (["field", "model"], "../../evil"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_descriptions_are_one_line_errors(good_model, tmp_path, case, capsys):
    keys, value = MALFORMED[case]
    hostile = rewrite(good_model, tmp_path / "h.apmgsrn", set_path(keys, value))
    with pytest.raises(ApmgsrnError, match="model file is inconsistent"):
        apmgsrn.load(hostile)
    assert main(["info", str(hostile)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000, "7", '"x"', "null", "{" * 50_000])
def test_description_json_that_is_deep_or_not_an_object_is_refused(good_model, tmp_path, text):
    hostile = rewrite(good_model, tmp_path / "h.apmgsrn", raw_description=text)
    with pytest.raises(ApmgsrnError, match="not an apmgsrn model file"):
        apmgsrn.load(hostile)


def test_a_stored_backend_is_ignored_so_a_gpu_trained_model_loads_anywhere(good_model, tmp_path):
    for backend in ("triton", "../../evil"):
        stored = rewrite(good_model, tmp_path / "b.apmgsrn", set_path(["field", "encoder", "backend"], backend))
        model = apmgsrn.load(stored)
        points = torch.rand(64, 3) * 2 - 1
        with torch.no_grad():
            assert torch.equal(model(points), apmgsrn.load(good_model)(points))


def test_nan_weights_and_singular_grid_maps_are_refused(good_model, tmp_path):
    def poison(name, value):
        def mutate(tensors):
            tensors[name] = torch.full_like(tensors[name], value)
        return mutate

    for name, value, reason in [("decoder.2.weight", float("nan"), "NaN or Inf"),
                                ("encoder.grids", float("inf"), "NaN or Inf"),
                                ("encoder.matrices", 0.0, "singular")]:
        hostile = rewrite(good_model, tmp_path / "h.apmgsrn", tensors=poison(name, value))
        with pytest.raises(ApmgsrnError, match=reason):
            apmgsrn.load(hostile)


def test_tensors_that_disagree_with_the_config_are_refused(good_model, tmp_path, no_module_built):
    cases = {
        "missing": lambda t: t.pop("decoder.4.weight"),
        "extra": lambda t: t.__setitem__("encoder.payload", torch.zeros(10)),
        "reshaped": lambda t: t.__setitem__("encoder.grids", t["encoder.grids"].reshape(2, 1, 8, 4, 2).contiguous()),
        "float64": lambda t: t.__setitem__("encoder.translations", t["encoder.translations"].double()),
    }
    for name, mutate in cases.items():
        hostile = rewrite(good_model, tmp_path / f"{name}.apmgsrn", tensors=mutate)
        with pytest.raises(ApmgsrnError, match="model file is inconsistent"):
            apmgsrn.load(hostile)


def test_header_claims_that_disagree_with_the_bytes_are_refused(good_model, tmp_path):
    data = bytearray(good_model.read_bytes())
    length = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + length])
    for name, mutate in {
        "shape larger than its bytes": lambda h: h["encoder.grids"].__setitem__("shape", [2, 1, 400, 400, 400]),
        "overlapping extents": lambda h: h["decoder.4.weight"].__setitem__("data_offsets", h["decoder.2.weight"]["data_offsets"]),
        "unknown dtype": lambda h: h["encoder.grids"].__setitem__("dtype", "OBJ"),
    }.items():
        changed = json.loads(json.dumps(header))
        mutate(changed)
        text = json.dumps(changed).encode()
        text += b" " * (length - len(text)) if len(text) <= length else b""
        path = tmp_path / "h.apmgsrn"
        path.write_bytes(len(text).to_bytes(8, "little") + text + bytes(data[8 + length :]))
        with pytest.raises(ApmgsrnError, match="not an apmgsrn model file"):
            apmgsrn.load(path)


def test_the_container_format_constants_are_what_files_carry(good_model):
    with open(good_model, "rb") as f:
        length = int.from_bytes(f.read(8), "little")
        meta = json.loads(f.read(length))["__metadata__"]
    assert meta["format"] == FORMAT and int(meta["format_version"]) == FORMAT_VERSION and meta["kind"] == "field"
    assert "backend" not in json.loads(meta["description"])["field"]["encoder"]


HOSTILE_SOURCES = {
    "attributes not an object": ("attributes", ["units"]),
    "an attribute of another type": ("attributes", {"units": {"nested": 1}}),
    "a NaN attribute": ("attributes", {"scale": float("nan")}),
    "too many attributes": ("attributes", {f"a{i}": i for i in range(300)}),
    "two dimension names": ("dimensions", ["z", "y"]),
    "coordinates of two axes": ("coordinates", [None, None]),
    "a coordinate without a name": ("coordinates", [None, None, {"start": 0, "step": 1}]),
    "an infinite step": ("coordinates", [None, None, {"name": "x", "start": 0, "step": float("inf")}]),
    "uneven values of the wrong count": ("coordinates", [None, None, {"name": "x", "start": 0, "step": 1,
                                                                       "values": [0, 1, 3]}]),
    "a compression level of 12": ("compression", {"zlib": True, "complevel": 12, "shuffle": True}),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_SOURCES))
def test_malformed_source_metadata_is_refused(good_model, tmp_path, case, no_module_built):
    key, value = HOSTILE_SOURCES[case]
    # json.dumps writes NaN and Infinity as Python's reader takes them back: the checks must catch them.
    hostile = rewrite(good_model, tmp_path / "h.apmgsrn", set_path(["source", key], value))
    with pytest.raises(ApmgsrnError, match="model file is inconsistent"):
        apmgsrn.load(hostile)


def test_source_metadata_round_trips(good_model, tmp_path):
    coordinates = [None, {"name": "lat", "start": 90.0, "step": -1.0, "attributes": {"units": "degrees_north"}},
                   {"name": "x", "start": 0.0, "step": 0.5, "values": [0, 0.1, 0.3, 0.6, 1.0, 1.5, 2.1, 3.5]}]
    path = rewrite(good_model, tmp_path / "m.apmgsrn", set_path(["source", "coordinates"], coordinates))
    source = apmgsrn.load(path).description.source
    assert source.metadata.coordinates[1].attributes == {"units": "degrees_north"}
    assert source.metadata.coordinates[2].values[-1] == 3.5 and source.metadata.coordinates[0] is None
    assert SourceInfo.from_dict(source.to_dict()) == source
