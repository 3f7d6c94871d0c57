"""The public Python API: fit a volume, open a model file, query, decode, save, render and export it.

Made for notebooks: numpy in, numpy (or an xarray DataArray) out, device names as strings, no output path
needed to fit, progress through ``tqdm.auto`` inside Jupyter (:mod:`apmgsrn.progress`)::

    model = apmgsrn.fit(volume, preset="small")          # a numpy array, an xarray DataArray or a file
    values = model.predict(points)                        # [N, 3] in [-1, 1]^3 -> [N]
    decoded = model.decode(shape=(64, 64, 64))            # xarray.DataArray (numpy without xarray)

Every bad argument of these functions is an :class:`~apmgsrn.errors.ApmgsrnError` naming it (never a
``TypeError``, ``AttributeError`` or ``MemoryError`` from inside): sizes are checked against the memory they
would take before anything is allocated, and every file written passes the output gate of
:mod:`apmgsrn.atomic`.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from apmgsrn.limits import LIMITS
from apmgsrn.arguments import check_choice, check_int, check_number
from apmgsrn.atomic import check_output_path, check_output_target
from apmgsrn.choices import PRESET_UNITS

import apmgsrn.decomposition.brick_model  # noqa: F401 - registers the brick-model loader
import apmgsrn.series  # noqa: F401 - registers the time-series loaders (files, brick folders)
from apmgsrn.data import ArrayVolume, Volume, open_volume
from apmgsrn.data.grid import AxisCoordinates, Region, VolumeMetadata, plain_attributes
from apmgsrn.series.data import parse_time
from apmgsrn.device import inference_dtype, resolve_device
from apmgsrn.errors import ApmgsrnError
from apmgsrn.export import export_onnx
from apmgsrn.inference.decode import decode_array, decode_volume
from apmgsrn.inference.query import query
from apmgsrn.io import ModelDescription, SourceInfo, open_model, save_field
from apmgsrn.io.container import SERIES_FILE_KINDS, check_replaceable
from apmgsrn.io.decode_plan import DecodePlan, plan_decode
from apmgsrn.io.description import check_time
from apmgsrn.io.field_file import FIELD_KIND
from apmgsrn.io.verify import FileCheck, verify_model
from apmgsrn.models.field import NeuralField
from apmgsrn.options import TrainOptions
from apmgsrn.planning import Plan, resolve
from apmgsrn.recipes import RUNTIME
from apmgsrn.rendering import Camera, RendererConfig, VolumeRenderer, extent_from_shape, make_transfer_function
from apmgsrn.rendering.images import as_uint8
from apmgsrn.rendering.raymarch import default_batch_size
from apmgsrn.training.callbacks import TrainingProgress
from apmgsrn.training.fit import fit as fit_prepared
from apmgsrn.training.fit import timed_config
from apmgsrn.training.fit import prepare_values
from apmgsrn.training.packing import pack_volume_model
from apmgsrn.series.file import save_series
from apmgsrn.series.fit import fit_series


class Model(nn.Module):
    """A model opened from a file: ``model(points)`` maps ``[N, 3]`` points in ``[-1, 1]^3`` to ``[N, 1]``
    values in data units.

    Points are ``(x, y, z)``; voxel ``i`` of an axis with ``n`` voxels sits at ``-1 + 2 i / (n - 1)``.

    Attributes:
        field: the network (a single field or a routed brick model).
        description: what its file says (volume shape, value range, source, training summary, bricks...).
        path: the file or folder it was opened from (None for a model fitted in memory).
    """

    def __init__(self, field: nn.Module, description: ModelDescription, path: str | os.PathLike | None = None):
        super().__init__()
        self.field = field
        self.description = description
        self.path = None if path is None else Path(path)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.field(points)

    @property
    def device(self) -> torch.device:
        """Where the network evaluates."""
        for parameter in self.parameters():
            return parameter.device
        return torch.device("cpu")

    def set_precision(self, precision: str) -> Model:
        """Choose the arithmetic of inference (decode, eval, render); training is not affected.

        Args:
            precision: ``"float32"`` (the fused float32 kernel on CPUs, exact to float32 rounding),
                ``"bfloat16"`` (the decoder's hidden layers in bfloat16: fast where the CPU multiplies it
                natively, a PSNR cost that docs/benchmarks.md measures), or ``"auto"`` (bfloat16 on such
                CPUs for a field without a fused float32 kernel, float32 elsewhere: on an AVX512-BF16 CPU the
                fused kernels of APMGSRN and the hybrid decoded 2.1-3.2x faster than bfloat16 matrix products,
                docs/benchmarks_decode.md).

        Returns:
            The model.

        Raises:
            InvalidArgument: an unknown precision.
        """
        dtype = inference_dtype(precision, self.device)
        for module in self.modules():
            if isinstance(module, NeuralField):
                module.inference_dtype = None if precision == "auto" and module.fused_inference() else dtype
        return self

    def predict(self, points, batch_size: int = RUNTIME.query_batch, time: int | None = None) -> np.ndarray:
        """Values at points, without gradients, in bounded-memory batches.

        Args:
            points: ``[..., 3]`` ``(x, y, z)`` in ``[-1, 1]^3`` (numpy, a list or a tensor). Outside points
                get the field's value there (zero features beyond every grid); a point with a NaN coordinate
                gives NaN.
            batch_size: points per forward pass.
            time: the time step of a time-series model (default: the first).

        Returns:
            float32 numpy array ``[...]`` of values in data units.

        Raises:
            ApmgsrnError: ``points`` is not ``[..., 3]`` numbers, their float32 copy would not fit in memory, or
                a time step the model lacks.
        """
        try:
            array = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else np.asarray(points)
        except (ValueError, TypeError) as exc:
            raise ApmgsrnError(f"points: {exc}; give [..., 3] numbers (x, y, z) in [-1, 1]",
                               arguments=("points",)) from None
        if array.ndim < 1 or array.shape[-1] != 3 or array.dtype.kind not in "uif":
            raise ApmgsrnError(f"points of shape {array.shape} ({array.dtype}): give [..., 3] numbers (x, y, z) "
                               "in [-1, 1]", arguments=("points",))
        count = array.size // 3  # a float32 copy of the points and their values
        _check_fits_in_memory(16 * count, f"points: {count:,} points as float32 with their values",
                              "query them in parts", "points")
        field = self.step_field(time)
        flat = torch.from_numpy(np.ascontiguousarray(array.reshape(-1, 3), dtype=np.float32))  # [N, 3]
        return query(field, flat, batch_size).numpy().reshape(array.shape[:-1])

    def step_field(self, time: int | None = None) -> nn.Module:
        """The network of one time step: a time-series model materialises that step's features once (as fast
        to evaluate as a single-step model); any other model is its own field.

        Args:
            time: the time step (default: the first).

        Raises:
            ApmgsrnError: a time step the model lacks.
        """
        step = check_time(self.description, time)
        return self.field if self.description.series is None else self.field.step_field(step)

    def plan_decode(self, shape: tuple[int, int, int] | None = None, region: Region | str | dict | None = None,
                    time: int | None = None, region_units: str = "index") -> DecodePlan:
        """What :meth:`decode` samples and writes (lattice, names, coordinates), without evaluating anything.

        Args: as :meth:`decode`.
        """
        return plan_decode(self.description, _shape(shape), _region(region, region_units), time)

    def decode(self, shape: tuple[int, int, int] | None = None, region: Region | str | dict | None = None,
               time: int | None = None, region_units: str = "index", batch_size: int = RUNTIME.query_batch) -> Any:
        """The model sampled on a lattice, with the names, attributes and coordinates of its source.

        Args:
            shape: ``(D, H, W)`` samples in array order (z, y, x), as the returned array's shape (default: the
                training volume's voxel spacing over the region).
            region: a box of the training volume: a :class:`~apmgsrn.data.grid.Region`, a text
                ``"X0:X1,Y0:Y1,Z0:Z1"`` or a dict ``{"x": (start, stop), ...}`` (default: the whole volume).
            time: the time step (default: the first).
            region_units: ``"index"`` (half-open voxel indices) or ``"coordinates"`` (a closed box in the
                source's coordinates) for a text or dict region.
            batch_size: points per forward pass.

        Returns:
            An ``xarray.DataArray`` ``[D, H, W]`` named after the source's variable, with its attributes, its
            dimension names and a coordinate per axis (the source's coordinates at the samples; voxel indices of
            the training volume where it had none); a float32 numpy array when xarray is not installed.

        Raises:
            ApmgsrnError: a region outside the volume, a bad shape or time step.
        """
        plan = self.plan_decode(shape, region, time, region_units)
        d, h, w = (int(n) for n in plan.shape)
        _check_fits_in_memory(4 * d * h * w, f"shape=({d}, {h}, {w}): the decoded array",
                              "pass a smaller shape or region, or write it slab by slab with save_decoded", "shape")
        values = decode_array(self.step_field(plan.time), plan.shape, batch_size=batch_size,
                              box=plan.grid.box())  # [D, H, W]
        try:
            import xarray
        except ImportError:
            return values
        coordinates = {axis.name: (axis.name, axis.values, axis.attributes) for axis in plan.axes}
        return xarray.DataArray(values, dims=tuple(axis.name for axis in plan.axes), coords=coordinates,
                                name=plan.variable, attrs=plan.variable_attributes)

    def save_decoded(self, out: str | os.PathLike, shape: tuple[int, int, int] | None = None,
                     region: Region | str | dict | None = None, time: int | None = None,
                     region_units: str = "index", batch_size: int = RUNTIME.query_batch,
                     progress: bool = False) -> DecodePlan:
        """Decode to a file (``.nc``, ``.vti``, ``.raw``, ``.npy``), slab by slab, written atomically.

        Args:
            out: the volume file.
            shape, region, time, region_units, batch_size: as :meth:`decode`.
            progress: show progress.

        Returns:
            The plan that was written (shape, variable, coordinates).

        Raises:
            ApmgsrnError: as :meth:`decode`; ``out`` is refused by the output gate
                (:func:`~apmgsrn.atomic.check_output_target`) or is not a volume format.
        """
        out = check_output_target(_path(out, "out"), "decoded volume")
        plan = self.plan_decode(shape, region, time, region_units)
        options = plan.writer_options()
        if self.path is not None:
            options["attributes"] = {"source_model": self.path.name}
        decode_volume(self.step_field(plan.time), Path(out), plan.shape, batch_size=batch_size, progress=progress,
                      box=plan.grid.box(), **options)
        return plan

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model to a ``.apmgsrn`` file, atomically (an older model there is replaced; any other
        file is refused).

        Raises:
            ApmgsrnError: a brick model (a folder: copy it), or a file there that is not an apmgsrn model.
        """
        if self.description.kind not in (FIELD_KIND, *SERIES_FILE_KINDS):
            raise ApmgsrnError(f"{path}: a {self.description.kind} model is a folder written by brick training; "
                               "copy the folder instead of saving it")
        path = check_output_path(_path(path, "path"), "model file")  # never a device, nor inside a brick folder
        check_replaceable(path, self.description.kind)
        if self.description.kind in SERIES_FILE_KINDS:  # a packed series saves as float32 (what it loaded as)
            save_series(path, self.field, self.description.source, self.description.training,
                        list(self.description.series.steps))
        else:
            save_field(path, self.field, self.description.source, self.description.training)
        return path

    def export_onnx(self, path: str | os.PathLike) -> Path:
        """Write the network as an ONNX graph (input ``points`` ``[N, 3]``, output ``values`` ``[N, 1]``).

        See :func:`apmgsrn.export.export_onnx`.
        """
        return export_onnx(self.field, _path(path, "path"), self.path)


def load(path: str | os.PathLike, device: torch.device | str = "cpu", precision: str = "float32") -> Model:
    """Open a model file or a brick-model folder; never executes code from it.

    Args:
        path: the ``.apmgsrn`` file or brick-model folder.
        device: where to put the network: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"auto"`` or a torch device.
        precision: arithmetic of inference, see :meth:`Model.set_precision`: float32 by default (exact to
            float32 rounding, so a packed file's error bound holds); ``"bfloat16"`` or ``"auto"`` (bfloat16 on
            CPUs with native bfloat16) trade accuracy for speed.

    Raises:
        ApmgsrnError: the file is missing, corrupt, foreign, hostile or from a newer version; an unknown device.
    """
    loaded = open_model(_path(path, "path"), _device(device))
    return Model(loaded.field, loaded.description, path).eval().set_precision(precision)


def verify(path: str | os.PathLike) -> list[FileCheck]:
    """Check a model file, training checkpoint or model folder for damage without evaluating it: every
    checksum, every description, every brick against its folder's manifest (``apmgsrn verify``).

    Returns:
        One :class:`~apmgsrn.io.verify.FileCheck` per file (``.ok``, ``.problem``, ``.line()``); problems are
        reported there, not raised.
    """
    return verify_model(path)


def plan(data, **options) -> Plan:
    """What :func:`fit` (and ``apmgsrn train``) would do with ``data`` and ``options``, resolved and trained on
    nothing: the model kind and size, the budget, the point draws, how a series trains and packs.

    Args:
        data: as :func:`fit`.
        options: the options of :func:`fit` (every option of ``apmgsrn train``, named with underscores:
            :class:`~apmgsrn.options.TrainOptions`).

    Returns:
        The frozen :class:`~apmgsrn.planning.Plan`; ``plan.to_dict()`` equals what
        ``apmgsrn train DATA ... --dry-run --json`` prints for the same options.

    Raises:
        ApmgsrnError: unreadable data, an unknown option, options that contradict each other.
    """
    given = TrainOptions.from_kwargs(**options)
    if isinstance(given.time, str):
        given = replace(given, time=parse_time(given.time))  # "all" or "A:B[:S]": a series along a time axis
    if isinstance(data, (str, os.PathLike)) or _is_path_list(data):
        return resolve([str(data)] if isinstance(data, (str, os.PathLike)) else [str(d) for d in data], given)
    return resolve(_as_volume(data, variable=given.variable, time=given.time, fill_nonfinite=given.fill_nonfinite),
                   given)


def fit(data, preset: str = "small", model: str | None = None, iterations: int | None = None,
        batch_size: int | None = None, device: torch.device | str = "auto", progress: bool = True,
        **options) -> Model:
    """Fit a model to a volume and return it, ready to query (nothing is written anywhere you see).

    Args:
        data: a 3-D numpy array ``[D, H, W]`` (z, y, x; x fastest), an ``xarray.DataArray`` (its name,
            attributes, dimensions and coordinates are kept for decoding) or a volume file path; or a time
            series (a list of files, a glob such as ``"run/*.vti"``, a ``.pvd``, or one file with ``time``
            ``"all"`` or ``"A:B[:S]"``), trained stepwise and packed as ``apmgsrn train`` does.
        preset: size preset, ``small``, ``medium`` or ``large``.
        model: model kind: ``hybrid`` (docs/models.md), ``apmgsrn`` (the paper's), ``fvsrn`` or ``ngp``; None:
            the plan's default (:func:`apmgsrn.choices.default_model`).
        iterations: training iterations (default: the recipe's budget for the device).
            ``minutes=M`` instead trains for about M minutes, the iterations sized to this machine first.
        batch_size: points per iteration (default: the recipe's for the device).
        device: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:I"`` or a torch device.
        progress: show training progress (a widget in Jupyter).
        options: every other option of ``apmgsrn train``, named with underscores
            (:class:`~apmgsrn.options.TrainOptions`): data (``variable``, ``time``, ``fill_nonfinite``), value
            transform (``transform``, ``log_offset``), model (``grids``, ``features``, ``resolution`` as an
            integer or three, ``hidden_layers``, ``width``, ...), training (``lr``, ``seed``, ``lr_schedule``,
            ``voxel_fraction``, ...), packing (``bits``, ``ratio``, ``size``, ``max_error``, ...) and a time
            series' steps (``start_step``, ``step_iterations``, ``step_lr``, ``step_sparsity``, ...).
            :func:`plan` shows what they resolve to.

    Returns:
        The fitted :class:`Model`; its ``description.training`` holds the PSNR, the largest error and the plan.

    Raises:
        ApmgsrnError: unreadable data, NaN/Inf voxels without ``fill_nonfinite``, an invalid option.
    """
    if isinstance(device, torch.device):
        device = str(device)
    resolved = plan(data, preset=preset, model=model, iterations=iterations, batch_size=batch_size, device=device,
                    **options)
    target = torch.device(resolved.device)
    if resolved.bricks is not None:
        raise ApmgsrnError("bricks=: a brick model trains one network per brick on workers, which the command "
                           "line runs (apmgsrn train)", arguments=("bricks",))
    if resolved.input == "series":
        return _fitted(lambda out: fit_series(resolved.source, resolved.field, resolved.training, out, target,
                                              transform=resolved.transform, log_offset=resolved.log_offset,
                                              progress=progress, stepwise=resolved.stepwise,
                                              packing=resolved.packing, plan=resolved.record()), target)
    volume = resolved.source
    truth = volume.to_numpy()  # [D, H, W] float32, data units
    prepared = prepare_values(truth, resolved.transform, resolved.log_offset, str(volume.path), target)

    train_config, extra = resolved.training, {"plan": resolved.record()}
    if resolved.minutes is not None:
        train_config, extra["time_budget"] = timed_config(prepared, resolved.field, train_config,
                                                          tuple(volume.shape), resolved.minutes,
                                                          log=print if progress else None)

    def train(out: Path) -> None:
        result = fit_prepared(prepared, truth, resolved.field, train_config, out, SourceInfo.of_volume(volume),
                              {}, callbacks=[TrainingProgress(enabled=progress)], summary_extra=extra)
        if resolved.packing is not None:
            training = result.packed_summary(resolved.training.batch_size, resolved.device)
            pack_volume_model(result.field, volume, resolved.packing, training, target, out,
                              log=print if progress else (lambda line: None))

    return _fitted(train, target)


def _fitted(write: Callable[[Path], object], device: torch.device) -> Model:
    """The model ``write(path)`` trains and saves, loaded back: the pipeline every fit goes through writes a
    file, and loading it gives exactly what :meth:`Model.save` writes. The file is a temporary one."""
    with tempfile.TemporaryDirectory(prefix="apmgsrn-fit-") as folder:
        out = Path(folder) / "model.apmgsrn"
        write(out)
        fitted = load(out, device)
    fitted.path = None
    return fitted


def _is_path_list(data) -> bool:
    return isinstance(data, (list, tuple)) and bool(data) and all(isinstance(d, (str, os.PathLike)) for d in data)


def render(
    model: Model,
    width: int = 512,
    height: int = 512,
    colormap: str = "Cool to Warm",
    value_range: tuple[float, float] | None = None,
    opacity: tuple[tuple[float, float], ...] | None = None,
    azimuth: float = 30.0,
    elevation: float = 20.0,
    distance: float | None = None,
    fov: float = 30.0,
    samples_per_ray: int = 256,
    preset_name: str | None = None,
    preset_units: str = "normalized",
) -> np.ndarray:
    """Volume-render a model (docs/method.md §7) to an RGBA image.

    Args:
        model: the model (:func:`fit` or :func:`load`).
        width, height: image size in pixels.
        colormap: a built-in name (``Cool to Warm``, ``viridis``...), a matplotlib name or a ParaView preset
            ``.json``/``.xml`` file.
        value_range: ``(min, max)`` of the transfer function (default: the model's value range).
        opacity: ``(position, alpha)`` pairs on 0..1 of the range (default: a preset's own, else a ramp).
        azimuth, elevation: camera angles in degrees (0 azimuth looks from -y; elevation above the xy plane).
        distance: camera distance from the centre (default: fit the box).
        fov: vertical field of view, degrees.
        samples_per_ray: samples across the box's longest side.
        preset_name: which preset of a file holding several.
        preset_units: ``normalized`` (stretch a preset over the range, as ParaView does) or ``data``.

    Returns:
        ``[height, width, 4]`` uint8 RGBA (colour not premultiplied; alpha is the ray's opacity).

    Raises:
        ApmgsrnError: a model that is no :class:`Model`, or any other bad argument (named).
    """
    if not isinstance(model, Model):
        raise ApmgsrnError(f"model={type(model).__name__}: give a Model (apmgsrn.load or apmgsrn.fit)",
                           arguments=("model",))
    device = model.device
    value_range = tuple(model.description.value_range) if value_range is None else _value_range(value_range)
    if not isinstance(colormap, (str, os.PathLike)):
        raise ApmgsrnError(f"colormap={colormap!r}: give a colour-map name or a preset file path",
                           arguments=("colormap",))
    if preset_name is not None and not isinstance(preset_name, str):
        raise ApmgsrnError(f"preset_name={preset_name!r}: give a preset's name", arguments=("preset_name",))
    check_choice("preset_units", preset_units, PRESET_UNITS)
    transfer_function = make_transfer_function(str(colormap), value_range, opacity=_opacity(opacity),
                                               preset_name=preset_name, preset_units=preset_units)
    extent = extent_from_shape(model.description.volume_shape)
    config = RendererConfig(samples_per_ray=samples_per_ray, batch_size=default_batch_size(device))
    renderer = VolumeRenderer(model.field, transfer_function, config, extent=extent, device=device)
    camera = Camera.orbit(azimuth, elevation, distance, fov, width, height, extent)
    return as_uint8(renderer.render(camera, alpha=True).image)  # [H, W, 4]


def _as_volume(data, variable: str | None = None, time: int | None = None,
              fill_nonfinite: float | None = None) -> Volume:
    """A volume from what a notebook holds: a numpy array, an xarray DataArray or a file path.

    Raises:
        ApmgsrnError: data of another type, or not 3-D.
    """
    if isinstance(data, (str, os.PathLike)):
        return open_volume(data, variable=variable, time=time, fill_nonfinite=fill_nonfinite)
    if type(data).__name__ == "DataArray" and hasattr(data, "dims"):  # xarray, without importing it
        return _data_array_volume(data, time, fill_nonfinite)
    if variable is not None or time is not None:
        raise ApmgsrnError("variable= and time= choose within a file or DataArray; a numpy array is one volume: "
                           "drop them", arguments=("variable", "time"))
    if isinstance(data, torch.Tensor):
        data = data.detach().cpu().numpy()
    array = np.asarray(data)
    if array.dtype.kind not in "uifb":
        raise ApmgsrnError(f"data of type {type(data).__name__} ({array.dtype}): give a 3-D numeric numpy array, "
                           "an xarray DataArray or a volume file path")
    return ArrayVolume(array, "array", fill_nonfinite=fill_nonfinite)


def _data_array_volume(array, time: int | None, fill_nonfinite: float | None) -> ArrayVolume:
    """An xarray DataArray as a volume that keeps its name, attributes, dimensions and coordinates."""
    if array.ndim == 4:
        if time is None and array.shape[0] != 1:
            raise ApmgsrnError(f"DataArray {array.name!r} has a {array.dims[0]} dimension of {array.shape[0]}; pass "
                               f"time=INDEX (0..{array.shape[0] - 1})", arguments=("time",))
        array = array.isel({array.dims[0]: time or 0})
    elif time is not None:
        raise ApmgsrnError(f"DataArray {array.name!r} has no time dimension; drop time=", arguments=("time",))
    dims = tuple(str(d) for d in array.dims)
    coordinates = []
    for dim in dims[-3:]:
        coordinate = array.coords.get(dim)
        values = None if coordinate is None else np.asarray(coordinate.values)
        if values is None or values.ndim != 1 or values.dtype.kind not in "uif" or not np.all(np.isfinite(values)):
            coordinates.append(None)  # no coordinate, or one that places nothing (dates, labels)
        else:
            coordinates.append(AxisCoordinates.from_values(dim, values, plain_attributes(dict(coordinate.attrs))))
    encoding = getattr(array, "encoding", {}) or {}
    compression = ({"zlib": True, "complevel": int(encoding.get("complevel") or 4),
                    "shuffle": bool(encoding.get("shuffle", True))} if encoding.get("zlib") else None)
    metadata = VolumeMetadata(
        attributes=plain_attributes(dict(array.attrs)),
        dimensions=dims if len(dims) == 3 else None,
        coordinates=tuple(coordinates) if any(c is not None for c in coordinates) else None,
        compression=compression,
    )
    name = None if array.name is None else str(array.name)
    return ArrayVolume(np.asarray(array.values), "DataArray", name, fill_nonfinite, metadata)


def _path(path, name: str) -> str | os.PathLike:
    """``path`` if it names a file (a text or an ``os.PathLike``).

    Raises:
        ApmgsrnError: anything else.
    """
    if isinstance(path, bytes) or not isinstance(path, (str, os.PathLike)) or not str(path):
        raise ApmgsrnError(f"{name}={path!r}: give a file path (a str or pathlib.Path)", arguments=(name,))
    return path


def _check_fits_in_memory(need: int, what: str, way_out: str, argument: str) -> None:
    """Refuse to allocate ``need`` bytes beyond the memory budget (half of what is free), before allocating.

    Raises:
        ApmgsrnError: ``"{what} takes {need} bytes, more than the memory budget; {way_out}"``, naming ``argument``.
    """
    from apmgsrn.data.opener import memory_budget

    if need > memory_budget():
        raise ApmgsrnError(f"{what} takes {need:,} bytes, more than the memory budget (half of what is free); "
                           f"{way_out}", arguments=(argument,))


def _value_range(value_range) -> tuple[float, float]:
    """``(min, max)``, two finite numbers with ``min < max``.

    Raises:
        ApmgsrnError: anything else.
    """
    try:
        low, high = value_range
        low, high = check_number("value_range", low), check_number("value_range", high)
    except (TypeError, ValueError):
        raise ApmgsrnError(f"value_range={value_range!r}: give (min, max), two finite numbers",
                           arguments=("value_range",)) from None
    if not low < high:
        raise ApmgsrnError(f"value_range={value_range!r}: min must be below max", arguments=("value_range",))
    return low, high


def _opacity(opacity) -> tuple[tuple[float, float], ...] | None:
    """``(position, alpha)`` pairs of finite numbers in [0, 1], or None.

    Raises:
        ApmgsrnError: anything else.
    """
    if opacity is None:
        return None
    try:
        pairs = tuple((check_number("opacity", x, 0.0, 1.0), check_number("opacity", a, 0.0, 1.0))
                      for x, a in opacity)
    except (TypeError, ValueError):
        pairs = ()
    if not pairs:
        raise ApmgsrnError(f"opacity={opacity!r}: give (position, alpha) pairs of numbers in [0, 1]",
                           arguments=("opacity",))
    return pairs


def _device(device: torch.device | str) -> torch.device:
    return device if isinstance(device, torch.device) else resolve_device(str(device))


def _shape(shape) -> tuple[int, int, int] | None:
    """``(D, H, W)``: three sizes from 1 to :attr:`~apmgsrn.limits.Limits.lattice_side`, or None.

    Raises:
        ApmgsrnError: anything else.
    """
    if shape is None:
        return None
    try:
        sizes = tuple(check_int("shape", n, 1, LIMITS.lattice_side) for n in shape)
    except (TypeError, ValueError):
        sizes = ()
    if len(sizes) != 3:
        raise ApmgsrnError(f"shape={shape!r}: give (D, H, W), three integer sizes from 1 to {LIMITS.lattice_side} in "
                           "array order (z, y, x)", arguments=("shape",))
    return sizes


def _region(region, units: str) -> Region | None:
    if region is None or isinstance(region, Region):
        return region
    if isinstance(region, str):
        return Region.parse(region, units)
    if isinstance(region, dict):
        unknown = set(region) - {"x", "y", "z"}
        if unknown:
            raise ApmgsrnError(f"region={region!r}: keys are x, y and z", arguments=("region",))
        return Region(**region, units=units)
    raise ApmgsrnError(f"region={region!r}: give a Region, a text X0:X1,Y0:Y1,Z0:Z1 or a dict of (start, stop)",
                       arguments=("region",))
