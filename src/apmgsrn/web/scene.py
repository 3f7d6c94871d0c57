"""What a web page needs of a model: its feature grids as one flat table described level by level, the
decoder's weights, the output scaling and the value transform, with every array coded for the page.

Every encoder the page renders is read as a list of *levels* (the form of :mod:`apmgsrn.ops.level_grids`):
a lattice of ``R_x x R_y x R_z`` vertices with ``F`` features each, reached from a point ``p`` by an affine map
``f = A' p + t'`` in index units, read trilinearly from its 8 vertices. A level is dense (vertex
``x + R_x (y + R_y z)``) or hashed (Instant-NGP's spatial hash modulo a power-of-two table); a *bounded* level
gives zero at a vertex outside its lattice (the hybrid's levels and every adaptive grid), an unbounded one
wraps a dense index and hashes any vertex (the NGP baseline, as tiny-cuda-nn does). Feature ``c`` of table row
``r`` of a level lives at ``offset + r * row_stride + c * feature_stride`` of the flat table, so each kind's
parameters go to the page as stored, without reordering.

Arrays travel as deflate (zlib) streams, base64 in the page, which the browser inflates natively: float32
as little-endian bytes, float16 tables as float16, and a packed file's quantised parameters as its integers
(zigzag, byte planes) and float16 group steps, rebuilt as ``level * step`` in float32 exactly as the loader
does (:func:`apmgsrn.io.quantization.dequantize`).
"""

from __future__ import annotations

import base64
import math
import zlib
from dataclasses import dataclass, field as dataclass_field
from pathlib import Path

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.io.packed import read_payload_file
from apmgsrn.io.quantization import group_ids
from apmgsrn.models.field import NeuralField
from apmgsrn.ops.level_grids import index_space_maps
from apmgsrn.rendering.camera import extent_from_shape

#: Deflate level of every coded array (9: the page is written once and read many times).
DEFLATE_LEVEL = 9
#: Model kinds the page renders (their encoders read as levels, see the module docstring).
WEB_MODEL_KINDS = ("hybrid", "apmgsrn", "ngp", "fvsrn")


@dataclass
class Blobs:
    """The coded arrays of a page, by id (``"b0"``, ``"b1"``, ...), and their bytes before base64."""

    entries: dict[str, dict] = dataclass_field(default_factory=dict)
    coded_bytes: int = 0

    def add(self, entry: dict, data: bytes) -> str:
        """Store ``data`` deflated under a new id with ``entry`` (how the page rebuilds float32 values)."""
        packed = zlib.compress(data, DEFLATE_LEVEL)
        self.coded_bytes += len(packed)
        key = f"b{len(self.entries)}"
        self.entries[key] = {**entry, "data": base64.b64encode(packed).decode("ascii")}
        return key

    def floats(self, values: torch.Tensor, float16: bool = False) -> str:
        """A float tensor as float32 (or float16, where it holds float16 values exactly) bytes."""
        array = values.detach().cpu().reshape(-1).numpy().astype(np.float32)
        if float16 and np.array_equal(array.astype(np.float16).astype(np.float32), array):
            return self.add({"encoding": "float16", "count": int(array.size)}, array.astype("<f2").tobytes())
        return self.add({"encoding": "float32", "count": int(array.size)}, array.astype("<f4").tobytes())

    def quantized(self, levels: np.ndarray, steps: np.ndarray, group: int) -> str:
        """Integers ``levels`` with one float16 step per ``group`` values: zigzag, the fewest whole bytes,
        byte planes (low bytes first), then the steps."""
        zigzag = ((levels.astype(np.int64) << 1) ^ (levels.astype(np.int64) >> 63)).astype(np.uint64)
        top = int(zigzag.max()) if zigzag.size else 0
        width = 1 if top < 1 << 8 else 2 if top < 1 << 16 else 4
        planes = b"".join(((zigzag >> (8 * k)) & 0xFF).astype(np.uint8).tobytes() for k in range(width))
        entry = {"encoding": "quantized", "count": int(levels.size), "width": width, "group": int(group),
                 "groups": int(steps.size)}
        return self.add(entry, planes + steps.astype("<f2").tobytes())


def _packed_integers(path: Path, kind: str, names: list[str], state: dict[str, torch.Tensor]
                     ) -> dict[str, tuple[np.ndarray, np.ndarray, int]]:
    """The integers and steps of a packed file's quantised parameters, as the file holds them.

    The steps are read from the start of each parameter's section; the integers are recovered from the
    loaded (dequantised, validated) values as ``round(value / step)`` and kept only where ``level * step``
    gives back every value exactly, so a parameter is never changed: it goes as float32 otherwise.

    Args:
        path: the packed file (already opened and checked by the loader).
        kind: its container kind.
        names: its parameters in the file's order.
        state: their loaded values.

    Returns:
        name -> (levels int64, float16 steps, group size) for each parameter recovered.
    """
    file = read_payload_file(path, kind, "a packed model")
    entries = file.description.get("tensors")
    out = {}
    if not isinstance(entries, list) or len(entries) != len(names):
        return out
    for name, entry, chunk in zip(names, entries, file.chunks[1:1 + len(names)]):
        if not (isinstance(entry, list) and entry and entry[0] == "quantized") or name not in state:
            continue
        values = state[name].detach().cpu().reshape(-1).numpy().astype(np.float32)
        group = int(entry[1])
        groups = -(-values.size // group)
        steps = np.frombuffer(chunk[: 2 * groups], dtype="<f2").astype(np.float16)
        if steps.size != groups or not (np.isfinite(steps).all() and (steps > 0).all()):
            continue
        per_element = steps.astype(np.float32)[group_ids(values.size, group)]
        levels = np.rint(values / per_element).astype(np.int64)
        if np.array_equal(levels.astype(np.float32) * per_element, values):
            out[name] = (levels, steps, group)
    return out


def _level(res, features, hashed, size, offset, row_stride, feature_stride, bounded=True) -> dict:
    return {"res": [int(r) for r in res], "features": int(features), "hashed": bool(hashed), "size": int(size),
            "offset": int(offset), "row_stride": int(row_stride), "feature_stride": int(feature_stride),
            "bounded": bool(bounded)}


def _maps_list(maps: torch.Tensor) -> list[list[float]]:
    """``[L, 3, 4]`` index-space maps as float32 numbers, row-major per level."""
    return [[float(v) for v in row] for row in maps.detach().cpu().float().reshape(-1, 12).tolist()]


def encoder_levels(field: NeuralField) -> tuple[list[dict], list[str], list[list[float]], int]:
    """The encoder of a single field as levels.

    Returns:
        (levels, the encoder parameters whose concatenation is the flat table, the levels' index-space maps,
        Fourier frequencies per axis (fV-SRN's sin/cos terms after the grid features; 0 elsewhere)).

    Raises:
        ApmgsrnError: a model kind the page cannot render.
    """
    model, encoder = field.config.model, field.encoder
    config = encoder.config
    if model == "hybrid":
        layout = encoder.layout
        levels = []  # domain levels, then the adaptive grids ([M, R, R, R, C] after the level table)
        for index in range(layout.levels):
            f = layout.features[index]
            levels.append(_level(layout.resolutions[index], f, layout.hashed[index], layout.sizes[index],
                                 layout.offsets[index], f, 1))
        return levels, ["level_table", "grids"], _maps_list(encoder.maps()), 0
    if model in ("apmgsrn", "fvsrn"):  # fV-SRN: one grid with the identity map, then its Fourier terms
        grids = encoder.grids if model == "apmgsrn" else encoder.grid  # [M, C, D, H, W]
        m, c, d, h, w = grids.shape
        vertices = d * h * w
        levels = [_level((w, h, d), c, False, vertices, g * c * vertices, 1, vertices) for g in range(m)]
        resolutions = torch.tensor([[w, h, d]] * m, dtype=torch.float32)
        if model == "apmgsrn":
            maps = index_space_maps(encoder.matrices.detach().float(), encoder.translations.detach().float(),
                                    resolutions)
        else:
            maps = index_space_maps(torch.eye(3)[None], torch.zeros(1, 3), resolutions)
        return levels, ["grids" if model == "apmgsrn" else "grid"], _maps_list(maps), \
            (config.frequencies if model == "fvsrn" else 0)
    if model == "ngp":
        scales = config.level_scales()
        resolutions = config.level_resolutions()
        sizes = config.level_table_sizes()
        f = config.features
        levels, maps, offset = [], [], 0
        for scale, n, size in zip(scales, resolutions, sizes):
            hashed = not n**3 <= size  # tiny-cuda-nn: dense where the (8-aligned) vertex count fits
            levels.append(_level((n, n, n), f, hashed, size, offset * f, f, 1, bounded=False))
            # vertex position u * s + 0.5 with u = (p + 1) / 2: f = (s / 2) p + (s / 2 + 0.5)
            half = np.float32(scale) * np.float32(0.5)
            maps.append([float(half), 0.0, 0.0, float(half + np.float32(0.5)),
                         0.0, float(half), 0.0, float(half + np.float32(0.5)),
                         0.0, 0.0, float(half), float(half + np.float32(0.5))])
            offset += size
        return levels, ["table"], maps, 0
    raise ApmgsrnError(f"a {model} model cannot be shown in a web page; it renders {', '.join(WEB_MODEL_KINDS)}")


def transform_entry(field) -> dict:
    t = field.transform
    return {"kind": t.kind, "offset": float(t.offset), "mean": float(t.mean), "std": float(t.std)}


def step_entry(field: NeuralField, blobs: Blobs, table_names: list[str], maps: list[list[float]],
               integers: dict | None = None, float16: bool = False) -> dict:
    """One step's arrays: the flat table's parts (in order), the maps, the decoder's layers."""
    integers = integers or {}
    parts = []
    for name in table_names:
        tensor = getattr(field.encoder, name)
        if f"encoder.{name}" in integers:
            parts.append(blobs.quantized(*integers[f"encoder.{name}"]))
        else:
            parts.append(blobs.floats(tensor, float16))
    layers = []
    for index, weight in enumerate(field.decoder.weights()):
        key = f"decoder.{2 * index}.weight"
        layers.append(blobs.quantized(*integers[key]) if key in integers else blobs.floats(weight))
    return {"table": parts, "maps": maps, "decoder": layers}


def field_shape(field: NeuralField, levels: list[dict], fourier: int) -> dict:
    """What does not change between steps: levels, decoder sizes, scaling, transform."""
    sizes = field.config.decoder.layer_sizes(field.encoder.out_features)
    return {
        "model": field.config.model,
        "levels": levels,
        "fourier": int(fourier),
        "decoder": sizes,
        "fit": [float(field.fit_min), float(field.fit_max)],
        "constant": field.value_min == field.value_max,
        "value_min": float(field.value_min),
        "transform": transform_entry(field),
    }


def packed_names(field: NeuralField) -> list[str]:
    """A single field's parameters in the file's order (the config's)."""
    return list(field.config.parameter_shapes())


def build_scene(path: str | Path, loaded, model_name: str) -> tuple[dict, Blobs, list[str]]:
    """The page's model: its shape, every step's arrays and the notes the page shows.

    Args:
        path: the model file.
        loaded: what the loader returned for it (``field``, ``description``).
        model_name: what the page calls it.

    Returns:
        (the scene as JSON-ready dict, its blobs, notes about what the page leaves out).

    Raises:
        ApmgsrnError: a brick model, or a model kind the page cannot render.
    """
    path = Path(path)
    description, field_ = loaded.description, loaded.field
    if description.bricks is not None:
        raise ApmgsrnError(f"{path}: a brick model cannot be shown in one web page yet; export a brick file of "
                           "its folder on its own")
    if description.model not in WEB_MODEL_KINDS:
        raise ApmgsrnError(f"{path}: a {description.model} model cannot be shown in a web page; it renders "
                           f"{', '.join(WEB_MODEL_KINDS)}")
    blobs, notes, steps = Blobs(), [], []
    float16 = getattr(description.config.encoder, "storage", "float32") == "float16"
    if description.series is not None:
        labels = [float(s.label) for s in description.series.steps]
        first = field_.step_field(0)
        levels, names, _, fourier = encoder_levels(first)
        for index in range(len(labels)):
            step = first if index == 0 else field_.step_field(index)
            _, _, maps, _ = encoder_levels(step)
            steps.append({**step_entry(step, blobs, names, maps, float16=float16), "label": labels[index]})
        shape_field = first
    else:
        levels, names, maps, fourier = encoder_levels(field_)
        integers = {}
        if description.packing is not None:
            state = dict(field_.named_parameters())
            integers = _packed_integers(path, description.kind, packed_names(field_), state)
            if description.packing.max_error is not None:
                notes.append(f"The file keeps |model - data| <= {description.packing.max_error:.4g} with a voxel "
                             "correction, which this page leaves out: it shows the network alone.")
        steps.append({**step_entry(field_, blobs, names, maps, integers, float16), "label": 0})
        shape_field = field_
    scene = {
        "format": "apmgsrn-web-1",
        "name": model_name,
        "volume_shape": list(description.volume_shape),
        "extent": list(extent_from_shape(description.volume_shape)),
        "value_range": [float(v) for v in description.value_range],
        "series": description.series is not None,
        "field": field_shape(shape_field, levels, fourier),
        "steps": steps,
    }
    return scene, blobs, notes


def check_finite(scene: dict) -> None:
    """Every map and scaling number is finite (the loader refused non-finite parameters already)."""
    numbers = [v for step in scene["steps"] for row in step["maps"] for v in row] + scene["field"]["fit"]
    if not all(math.isfinite(v) for v in numbers):
        raise ApmgsrnError(f"{scene['name']}: the model holds non-finite placement or scaling numbers")
