"""Hostile and malformed model files, built on the fly: each is refused with one ApmgsrnError line (the
CLI's exit 2) before anything is built from it, or loads correctly where that is the right answer."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SourceInfo, save_field
from apmgsrn.io.container import FORMAT, FORMAT_VERSION, sealed_file_bytes
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
    """A copy of ``path`` with its description (or raw description text, or tensors) replaced, its checksums
    made anew (a hostile writer can: they detect damage, not forgery)."""
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
    out.write_bytes(sealed_file_bytes(stored, meta))
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


def test_a_header_read_while_a_writer_replaces_the_file_sees_one_whole_file(good_model, tmp_path, monkeypatch):
    """A checkpoint is replaced atomically while another process may read it (a watcher, a resumed run): the
    reader must take the size from the file it opened, never from the path, which may already be the next file.
    Here the writer's replacement lands exactly between the reader's checks of the path and its open."""
    import builtins
    import os

    from apmgsrn.io import container

    larger = rewrite(good_model, tmp_path / "larger.apmgsrn", description=lambda d: d.__setitem__("note", "x" * 20_000))
    target = tmp_path / "watched.apmgsrn"
    target.write_bytes(good_model.read_bytes())

    def replaced_then_opened(path, *args, **kwargs):
        if Path(path) == target:
            os.replace(larger, target)
        return builtins.open(path, *args, **kwargs)

    monkeypatch.setattr(container, "open", replaced_then_opened, raising=False)
    header = container.read_header(target)
    assert header.description["note"] == "x" * 20_000
    assert header.tensors == container.read_header(good_model).tensors


def test_the_container_format_constants_are_what_files_carry(good_model):
    with open(good_model, "rb") as f:
        length = int.from_bytes(f.read(8), "little")
        meta = json.loads(f.read(length))["__metadata__"]
    assert meta["format"] == FORMAT and int(meta["format_version"]) == FORMAT_VERSION and meta["kind"] == "field"
    assert "backend" not in json.loads(meta["description"])["field"]["encoder"]


# ---------------------------------------------------------------------------------------- packed files
def packed_parts(field, correction=None) -> tuple[dict, list[bytes]]:
    """The description and the raw sections of a packed file of ``field`` (8 bits, optional correction)."""
    from apmgsrn.io.packed import packed_file_bytes
    from apmgsrn.training.packing import bits_quantizer, encode_field

    tensors, _ = encode_field(field, bits_quantizer(field, 8))
    data = packed_file_bytes(field, tensors, SourceInfo(path="v.npy"), {"iterations": 3}, {"psnr": 40.0}, correction)
    return split_packed(data)


def split_packed(data: bytes) -> tuple[dict, list[bytes]]:
    from apmgsrn.io import codec

    length = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + length])
    payload = data[8 + length :]
    sizes = json.loads(header["__metadata__"]["description"])["sections"]
    offsets = [sum(sizes[:i]) for i in range(len(sizes) + 1)]
    sections = [payload[offsets[i] : offsets[i + 1]] for i in range(len(sizes))]
    description = json.loads(codec.decompress_description(sections[0], 1 << 20, "d"))
    return description, sections[1:]


def write_packed_parts(path: Path, description: dict, sections: list[bytes], sizes: list[int] | None = None,
                       coding: str | None = "deflate-primer-1") -> Path:
    """A packed file of these parts (``sizes``: section sizes to declare instead of the true ones; ``coding``:
    the description coding the header names, None for none, which means LZMA)."""
    from apmgsrn.io import codec
    from apmgsrn.io.container import PACKED_KIND, file_bytes

    text = description if isinstance(description, bytes) else json.dumps(description).encode()
    coded = codec.compress_description(text) if coding == "deflate-primer-1" else codec.compress(text, "text")
    parts = [coded, *sections]
    payload = torch.frombuffer(bytearray(b"".join(parts)), dtype=torch.uint8)
    declared = sizes if sizes is not None else [len(p) for p in parts]
    header = {"sections": declared, **({"coding": coding} if coding is not None else {})}
    path.write_bytes(file_bytes({"payload": payload}, PACKED_KIND, header))
    return path


@pytest.fixture()
def good_packed_parts(good_model):
    from apmgsrn.io.packed import VoxelCorrection

    field = apmgsrn.load(good_model).field
    correction = VoxelCorrection(0.5, 0.9, np.array([0, 5, 200, 335], dtype=np.int64),
                                 np.array([1, -2, 3, 1], dtype=np.int64))
    return packed_parts(field, correction)


def test_a_good_packed_file_loads(good_packed_parts, tmp_path):
    description, sections = good_packed_parts
    model = apmgsrn.load(write_packed_parts(tmp_path / "p.apmgsrn", description, sections))
    assert model.description.packing.corrected_voxels == 4 and model.description.packing.max_error == 0.5


def test_packed_files_of_format_version_1_load(good_packed_parts, tmp_path, monkeypatch):
    """Version 1 coded the description with LZMA and named no coding; such files still load, the same."""
    from apmgsrn.io import container

    description, sections = good_packed_parts
    current = apmgsrn.load(write_packed_parts(tmp_path / "v2.apmgsrn", description, sections))
    monkeypatch.setattr(container, "FORMAT_VERSION", 1)
    old = write_packed_parts(tmp_path / "v1.apmgsrn", description, sections, coding=None)
    monkeypatch.undo()
    loaded = apmgsrn.load(old)
    assert loaded.description.format_version == 1 and current.description.format_version == FORMAT_VERSION
    points = torch.rand(1000, 3) * 2 - 1
    assert torch.equal(loaded.field(points), current.field(points))


@pytest.mark.parametrize("coding", ["lzma", None, 7])
def test_packed_description_codings_other_than_the_header_names_are_refused(good_packed_parts, tmp_path, coding):
    """A version-2 file must name the primed deflate coding; anything else (or nothing) is not ours."""
    description, sections = good_packed_parts
    hostile = write_packed_parts(tmp_path / "h.apmgsrn", description, sections, coding=coding)
    with pytest.raises(ApmgsrnError, match="not an apmgsrn model file"):
        apmgsrn.load(hostile)


def _set(keys, value):
    return lambda description, sections: set_path(keys, value)(description)


def _section(index, data):
    def mutate(description, sections):
        sections[index] = data(sections[index]) if callable(data) else data
    return mutate


def _correction(description, sections, index, values):
    """Replace the correction's gaps (``index`` -2) or values (-1) by ``values``, coded as the file declares."""
    from apmgsrn.io import codec

    width = description["correction"]["gap_width" if index == -2 else "level_width"]
    sections[index] = codec.compress(codec.to_bytes(np.array(values), width))


PACKED_HOSTILE = {
    # Size claims: refused from the description, before any section is decompressed or a module built.
    "resolution 300^3": (_set(["field", "encoder", "resolution"], [300, 300, 300]), "inconsistent"),
    "100,000 grids": (_set(["field", "encoder", "grids"], 100_000), "inconsistent"),
    "a correction on every voxel, coded in 20 bytes": (_set(["correction", "count"], 336), "corrupt"),
    "2^24 corrections in 18 bytes": (lambda d, s: (_set(["volume_shape"], [256, 256, 256])(d, s),
                                                   _set(["correction", "count"], 1 << 24)(d, s)),
                                     "more than its [0-9]+ stored bytes can hold"),
    "more corrections than voxels": (_set(["correction", "count"], 10**12), "inconsistent"),
    "volume of 2^72 voxels": (_set(["volume_shape"], [1 << 24, 1 << 24, 1 << 24]), "inconsistent"),
    "a group of zero": (_set(["tensors", 0, 1], 0), "inconsistent"),
    "predictor unknown": (_set(["tensors", 0, 2], "exec"), "inconsistent"),
    "width 3": (_set(["tensors", 0, 3], 3), "inconsistent"),
    "encoding pickle": (_set(["tensors", 1], ["pickle"]), "inconsistent"),
    "a tensor fewer": (lambda d, s: d["tensors"].pop(), "inconsistent"),
    "correction keys": (_set(["correction", "exec"], 1), "inconsistent"),
    "correction bound negative": (_set(["correction", "max_error"], -1.0), "inconsistent"),
    "report nested": (_set(["packing", "psnr"], {"a": 1}), "inconsistent"),
    # Sections that lie about what they hold.
    "grid section corrupt": (_section(0, lambda b: b[:4] + bytes(len(b) - 4)), "corrupt"),
    "grid section truncated": (_section(0, lambda b: b[: len(b) // 2]), "corrupt|inconsistent"),
    "steps NaN": (_section(0, lambda b: b"\xff\x7f" + b[2:]), "not positive and finite"),
    "correction index outside": (lambda d, s: _correction(d, s, -2, [0, 10, 250, 255]), "outside the volume"),
    "correction indices repeat": (lambda d, s: _correction(d, s, -2, [0, 0, 2, 2]), "strictly increasing"),
    "correction value zero": (lambda d, s: _correction(d, s, -1, [2, 0, 2, 2]), "zero value"),
}


@pytest.mark.parametrize("case", sorted(PACKED_HOSTILE))
def test_hostile_packed_files_are_one_line_errors(good_packed_parts, tmp_path, case, capsys):
    description, sections = json.loads(json.dumps(good_packed_parts[0])), list(good_packed_parts[1])
    mutate, message = PACKED_HOSTILE[case]
    mutate(description, sections)
    hostile = write_packed_parts(tmp_path / "h.apmgsrn", description, sections)
    with pytest.raises(ApmgsrnError, match=message):
        apmgsrn.load(hostile)
    assert main(["info", str(hostile)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err


def test_packed_size_claims_are_refused_before_a_module_is_built(good_packed_parts, tmp_path, monkeypatch):
    description, sections = json.loads(json.dumps(good_packed_parts[0])), list(good_packed_parts[1])
    description["field"]["encoder"]["resolution"] = [300, 300, 300]
    hostile = write_packed_parts(tmp_path / "h.apmgsrn", description, sections)

    def refuse(*args, **kwargs):
        raise AssertionError("a module was built from a file that should have been refused first")
    monkeypatch.setattr(field_module.NeuralField, "__init__", refuse)
    with pytest.raises(ApmgsrnError, match="inconsistent"):
        apmgsrn.load(hostile)


def test_packed_section_lists_that_disagree_with_the_payload_are_refused(good_packed_parts, tmp_path):
    description, sections = good_packed_parts
    true_sizes = [len(codec_text(description))] + [len(s) for s in sections]
    for sizes in ([*true_sizes[:-1], true_sizes[-1] + 1], true_sizes[:-1], [-1, *true_sizes[1:]],
                  ["1", *true_sizes[1:]], []):
        hostile = write_packed_parts(tmp_path / "h.apmgsrn", description, sections, sizes=sizes)
        with pytest.raises(ApmgsrnError, match="not an apmgsrn model file|inconsistent"):
            apmgsrn.load(hostile)


def codec_text(description: dict) -> bytes:
    from apmgsrn.io import codec

    return codec.compress_description(json.dumps(description).encode())


def test_a_packed_description_that_inflates_past_its_limit_is_refused(good_packed_parts, tmp_path):
    description, sections = good_packed_parts
    # A JSON object padded to 4 MiB of spaces: a few KB compressed, refused at 1 MiB.
    bomb = json.dumps(description).encode() + b" " * (4 << 20)
    hostile = write_packed_parts(tmp_path / "h.apmgsrn", bomb, sections)
    assert hostile.stat().st_size < 64 << 10
    with pytest.raises(ApmgsrnError, match="longer than"):
        apmgsrn.load(hostile)


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
