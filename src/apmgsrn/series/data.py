"""Time series of volumes: several files, a time dimension, or a ParaView ``.pvd`` collection.

:func:`open_series` turns what a user names into a :class:`VolumeSeries`: an ordered list of steps that
are opened one at a time, when read. Three ways to name a series:

- several files (a list, or one quoted glob pattern such as ``"run/*.vti"``): ordered by the number in
  each name that differs between the files; the numbers must step evenly (a missing step is an error);
- one NetCDF/HDF5/Zarr variable with a leading time dimension, with ``time="all"`` or ``"A:B[:S]"``;
- a ParaView ``.pvd`` collection: its data sets in order of their ``timestep``.

Every step must hold the same variable with the same shape, dtype and grid geometry (origin and spacing, or
coordinates) as the first; a step that does not is named in a one-line :class:`~apmgsrn.errors.ApmgsrnError`
when it is opened (every step is, for its fingerprint, before training). Every step's time value must be a
finite number.
"""

from __future__ import annotations

import glob
import math
import numbers
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apmgsrn.limits import LIMITS
from apmgsrn.data.fingerprint import volume_fingerprint
from apmgsrn.data.grid import AxisCoordinates
from apmgsrn.data.opener import check_regular, read_regular
from apmgsrn.data.readers import open_volume
from apmgsrn.data.volume import Volume, format_xyz
from apmgsrn.errors import ApmgsrnError

#: Characters that make an input a glob pattern rather than a file name.
GLOB_CHARACTERS = "*?["


@dataclass(frozen=True)
class TimeSelection:
    """Steps along a time dimension: ``all``, or ``A:B[:S]`` as in Python (``stop`` exclusive).

    Attributes:
        start: first index (None: 0).
        stop: index after the last (None: the end).
        step: stride (positive).
    """

    start: int | None = None
    stop: int | None = None
    step: int = 1

    def indices(self, length: int, where: str = "") -> range:
        """The selected indices of a time axis of ``length`` steps.

        Raises:
            ApmgsrnError: the selection is empty or reaches past the axis.
        """
        for bound in (self.start, self.stop):
            if bound is not None and not -length <= bound <= length:
                raise ApmgsrnError(
                    f"{where}: time={self} reaches past the time dimension of {length} steps; use indices 0..{length}",
                    arguments=("time",),
                )
        selected = range(length)[slice(self.start, self.stop, self.step)]
        if len(selected) == 0:
            raise ApmgsrnError(f"{where}: time={self} selects no step of the {length}; e.g. time=all",
                               arguments=("time",))
        return selected

    def __str__(self) -> str:
        if self.start is None and self.stop is None and self.step == 1:
            return "all"
        text = f"{'' if self.start is None else self.start}:{'' if self.stop is None else self.stop}"
        return text + (f":{self.step}" if self.step != 1 else "")


def parse_time(text: str) -> int | TimeSelection:
    """Parse ``--time``: an index (one step), ``all``, or ``A:B[:S]`` (a range of steps).

    Args:
        text: what the user typed.

    Returns:
        An ``int`` for one step, else a :class:`TimeSelection`.

    Raises:
        ApmgsrnError: anything else.
    """
    text = str(text).strip()
    if text.lower() == "all":
        return TimeSelection()
    if re.fullmatch(r"-?\d+", text):
        return int(text)
    parts = text.split(":")
    if len(parts) in (2, 3) and all(re.fullmatch(r"-?\d*", p) for p in parts):
        start, stop = (int(p) if p else None for p in parts[:2])
        step = int(parts[2]) if len(parts) == 3 and parts[2] else 1
        if step > 0:
            return TimeSelection(start, stop, step)
    raise ApmgsrnError(f"time={text!r}: give an index (e.g. 3), 'all', or a range A:B[:S] such as 0:30:2",
                       arguments=("time",))


@dataclass(frozen=True)
class SeriesStep:
    """Where one step's data is: a file, and an index along its time dimension (None: none)."""

    path: Path
    time: int | None = None

    def name(self) -> str:
        return self.path.name + (f"[t={self.time}]" if self.time is not None else "")


class VolumeSeries:
    """An ordered series of volumes on one grid, each step opened only when it is read.

    Attributes:
        steps: where each step is.
        labels: the number of each step (the number in a file name, the ``.pvd`` timestep, or the index
            along a time dimension).
        shape: ``(D, H, W)`` of every step.
        dtype: stored dtype of every step.
        variable: the variable every step holds (None for raw and npy files).
        coordinates: where the voxels of every step lie (the first step's ``metadata.coordinates``).
        options: the :func:`~apmgsrn.data.open_volume` options every step is opened with.

    Raises:
        ApmgsrnError: no step, a time value that is not a finite number, or a first step that cannot be read.
    """

    def __init__(self, steps: Sequence[SeriesStep], labels: Sequence[float], options: dict | None = None) -> None:
        if not steps:
            raise ApmgsrnError("a series needs at least one step")
        self.steps = tuple(steps)
        self.labels = tuple(labels)
        for step, label in zip(self.steps, self.labels):
            if isinstance(label, bool) or not isinstance(label, numbers.Real) or not math.isfinite(label):
                raise ApmgsrnError(f"{step.path}: its time value {label!r} is not a finite number; every step of a "
                                   "series needs one (a .pvd's timestep=)")
        self.options = dict(options or {})
        first = self._open(0)
        try:
            self.shape = first.shape
            self.dtype = first.dtype
            self.variable = first.variable
            self.coordinates = first.metadata.coordinates
        finally:
            first.close()

    def __len__(self) -> int:
        return len(self.steps)

    @property
    def path(self) -> Path:
        """The first step's file (what messages and model files name the series by)."""
        return self.steps[0].path

    def absolute(self) -> VolumeSeries:
        """The same series with absolute paths (for workers that reopen the files from another folder)."""
        steps = [SeriesStep(step.path.absolute(), step.time) for step in self.steps]
        return VolumeSeries(steps, self.labels, self.options)

    def subseries(self, indices: Sequence[int]) -> VolumeSeries:
        """The steps ``indices`` (in that order) as a series of their own, e.g. one group of a long run."""
        return VolumeSeries([self.steps[i] for i in indices], [self.labels[i] for i in indices], self.options)

    def _open(self, index: int) -> Volume:
        step = self.steps[index]
        return open_volume(step.path, time=step.time, **self.options)

    def volume(self, index: int) -> Volume:
        """Open step ``index``, checked against the first step.

        Raises:
            ApmgsrnError: the step holds another variable, shape, dtype or grid geometry than the first.
        """
        volume = self._open(index)
        if index == 0:
            return volume
        first = self.steps[0].name()
        where = f"{volume.path}: step {index} ({self.steps[index].name()})"
        problem = None
        if volume.variable != self.variable:
            problem = (f"holds {volume.variable!r} but step 0 ({first}) holds {self.variable!r}; "
                       "pass --variable NAME to read the same one from every step")
        elif volume.shape != self.shape:
            problem = (f"is {format_xyz(volume.shape)} (x*y*z) but step 0 ({first}) is {format_xyz(self.shape)}; "
                       "every step of a series must lie on the same grid")
        elif volume.dtype != self.dtype:
            problem = (f"stores {volume.dtype} but step 0 ({first}) stores {self.dtype}; convert the steps to one "
                       "type or train them separately")
        else:
            axis = geometry_difference(self.coordinates, volume.metadata.coordinates)
            if axis is not None:
                problem = (f"lies elsewhere along {axis} than step 0 ({first}): another origin, spacing or "
                           "coordinates; every step of a series must lie on the same grid")
        if problem is not None:
            volume.close()
            raise ApmgsrnError(f"{where} {problem}")
        return volume

    def read(self, index: int, z: slice = slice(None), y: slice = slice(None), x: slice = slice(None)) -> np.ndarray:
        """A region of step ``index`` as float32 ``[d, h, w]`` (the whole step by default); the file is closed after."""
        with self.volume(index) as volume:
            return volume.read(z, y, x)

    def iter_steps(self) -> Iterator[tuple[int, np.ndarray]]:
        """Every step in order, ``(index, float32 [D, H, W])``, one in memory at a time."""
        for index in range(len(self)):
            yield index, self.read(index)

    def to_numpy(self) -> np.ndarray:
        """Every step, ``[T, D, H, W]`` float32 (read one step at a time into one array)."""
        out = np.empty((len(self), *self.shape), dtype=np.float32)
        for index, data in self.iter_steps():
            out[index] = data
        return out

    @property
    def raw_bytes(self) -> int:
        """Size of the series as float32: ``T * D * H * W * 4`` bytes."""
        return len(self) * int(np.prod(self.shape)) * 4

    def step_name(self, index: int) -> str:
        """The file (and time index) of step ``index``, for messages and tables."""
        return self.steps[index].name()

    def describe(self) -> str:
        """One line: the steps, the variable, dims (x*y*z) and dtype.

        Returns:
            E.g. ``"30 steps 030_density_030_064_2.0.vti .. 059_density_059_064_2.0.vti:ImageFile 64x64x64
            (x*y*z) float32"``.
        """
        names = self.step_name(0) if len(self) == 1 else f"{self.step_name(0)} .. {self.step_name(len(self) - 1)}"
        variable = f":{self.variable}" if self.variable else ""
        return f"{len(self)} steps {names}{variable} {format_xyz(self.shape)} (x*y*z) {self.dtype}"

    def __repr__(self) -> str:
        return f"<VolumeSeries {self.describe()}>"


def geometry_difference(first, other) -> str | None:
    """The first axis (``"x"``, ``"y"``, ``"z"``) on which two volumes' coordinates
    (:attr:`~apmgsrn.data.grid.VolumeMetadata.coordinates`, ``(z, y, x)`` or None) place their voxels
    differently, or None where they agree. Coordinates a format does not give are voxel indices (start 0,
    step 1), so a file without geometry agrees with one whose origin is 0 and spacing 1."""
    for name, a, b in zip("zyx", _axes(first), _axes(other)):
        if not _same_axis(a, b):
            return name
    return None


def _axes(coordinates) -> tuple:
    return (None, None, None) if coordinates is None else tuple(coordinates)


def _same_axis(a: AxisCoordinates | None, b: AxisCoordinates | None) -> bool:
    a, b = a or AxisCoordinates("index"), b or AxisCoordinates("index")
    if a.even != b.even:
        return False
    if not a.even:
        scale = float(np.abs(np.asarray(a.values, dtype=np.float64)).max(initial=0.0))
        return len(a.values) == len(b.values) and bool(np.allclose(a.values, b.values, rtol=1e-9, atol=1e-9 * scale))
    scale = max(abs(a.step), abs(b.step))
    return (math.isclose(a.step, b.step, rel_tol=1e-9)
            and math.isclose(a.start, b.start, rel_tol=1e-9, abs_tol=1e-9 * scale))


def is_series_input(inputs: str | Path | Sequence[str | Path], time: object = None) -> bool:
    """Whether inputs name a series: several files, a glob pattern, a ``.pvd`` file, or a time range.

    Args:
        inputs: one path or pattern, or several paths.
        time: the ``--time`` value (an int picks one step; a :class:`TimeSelection` makes a series).
    """
    if isinstance(inputs, (str, Path)):
        inputs = [inputs]
    if len(inputs) > 1 or isinstance(time, TimeSelection):
        return True
    text = str(inputs[0])
    if Path(text).suffix.lower() == ".pvd":
        return True
    return any(c in text for c in GLOB_CHARACTERS) and not Path(text).exists()


def open_series(
    inputs: str | Path | Sequence[str | Path],
    variable: str | None = None,
    time: int | TimeSelection | None = None,
    shape: tuple[int, int, int] | None = None,
    dtype: str | None = None,
    fill_nonfinite: float | None = None,
) -> VolumeSeries:
    """Open a series lazily: only the first step is opened here (for its shape, variable and dtype).

    Args:
        inputs: several files, one glob pattern, a ``.pvd`` file, or one file with a time dimension.
        variable: the variable every step holds (default: the only 3-D one).
        time: for one file with a time dimension: a :class:`TimeSelection` (``all`` or ``A:B[:S]``).
        shape, dtype: of raw files (as for :func:`~apmgsrn.data.open_volume`).
        fill_nonfinite: replace NaN/Inf by this value in every step.

    Returns:
        The series.

    Raises:
        ApmgsrnError: no file matches, names that cannot be ordered, a gap in the numbering, a ``--time``
            that does not apply, or a damaged ``.pvd`` file.
    """
    paths = [inputs] if isinstance(inputs, (str, Path)) else list(inputs)
    if not paths:
        raise ApmgsrnError("no input files given; pass several files, a quoted glob such as 'run/*.vti' or a .pvd")
    options = {"variable": variable, "shape": shape, "dtype": dtype, "fill_nonfinite": fill_nonfinite}
    if len(paths) == 1 and Path(paths[0]).suffix.lower() == ".pvd":
        if time is not None:
            raise ApmgsrnError(f"{paths[0]}: time= does not apply to a .pvd collection; drop time=",
                               arguments=("time",))
        steps, labels = _pvd_steps(Path(paths[0]))
        return VolumeSeries(steps, labels, options)
    if len(paths) == 1 and not is_series_input(paths):
        return _time_axis_series(Path(paths[0]), time, options)
    if time is not None:
        raise ApmgsrnError("time= applies to one file with a time dimension, not to a list of files; drop time=",
                           arguments=("time",))
    files = _expand(paths)
    numbered = order_by_step_number(files)
    return VolumeSeries([SeriesStep(path) for _, path in numbered], [number for number, _ in numbered], options)


def input_files(inputs: str | Path | Sequence[str | Path]) -> list[Path]:
    """Every file a series input reads (a ``.pvd`` and the files it lists; the files a glob matches), so that a
    command can refuse to write onto any of them.

    Raises:
        ApmgsrnError: a pattern that matches nothing, a missing file, or a damaged ``.pvd``.
    """
    paths = [inputs] if isinstance(inputs, (str, Path)) else list(inputs)
    if len(paths) == 1 and Path(paths[0]).suffix.lower() == ".pvd":
        return [Path(paths[0]), *(step.path for step in _pvd_steps(Path(paths[0]))[0])]
    return _expand(paths)


def _time_axis_series(path: Path, time: int | TimeSelection | None, options: dict) -> VolumeSeries:
    if not isinstance(time, TimeSelection):
        raise ApmgsrnError(
            f"{path}: one file is a series only along its time dimension; pass time=all (or A:B[:S]), "
            "or give several files", arguments=("time",)
        )
    with open_volume(path, time=0, **options) as first:
        length = first.time_steps
    indices = time.indices(length, str(path))
    return VolumeSeries([SeriesStep(path, t) for t in indices], list(indices), options)


def _expand(paths: list) -> list[Path]:
    """Files of a list, each entry a file or a glob pattern (the shell did not expand a quoted one)."""
    files: list[Path] = []
    for entry in paths:
        text = str(entry)
        if any(c in text for c in GLOB_CHARACTERS) and not Path(text).exists():
            matched = sorted(glob.glob(str(Path(text).expanduser())))
            if not matched:
                raise ApmgsrnError(f"{text}: no file matches this pattern; check the folder and the pattern")
            files.extend(Path(m) for m in matched)
        else:
            files.append(Path(text).expanduser())
    for path in files:
        if not path.exists():
            raise ApmgsrnError(f"{path}: no such file or directory; check the path")
    return files


def order_by_step_number(files: Sequence[Path]) -> list[tuple[int, Path]]:
    """Order files by the step number in their names, and check that no step is missing.

    The step number is the first number in the names that is not the same in every name (so
    ``030_density_030_064_2.0.vti`` .. ``059_density_059_064_2.0.vti`` are steps 30..59). The numbers must
    rise by one stride (the smallest difference): a missing step is an error.

    Args:
        files: the files, in any order.

    Returns:
        ``(step number, file)`` in step order.

    Raises:
        ApmgsrnError: names without a distinguishing number, two files of one step, or a gap.
    """
    if len(files) == 1:
        numbers = re.findall(r"\d+", files[0].name)
        return [(int(numbers[0]) if numbers else 0, files[0])]
    numbers = [re.findall(r"\d+", path.name) for path in files]
    counts = {len(n) for n in numbers}
    if len(counts) != 1:
        fewest = min(range(len(files)), key=lambda i: len(numbers[i]))
        most = max(range(len(files)), key=lambda i: len(numbers[i]))
        raise ApmgsrnError(
            f"{files[fewest]}: its name holds {len(numbers[fewest])} number(s) but {files[most].name} holds "
            f"{len(numbers[most])}; cannot tell the step number: name the steps alike (e.g. run_0010.vti)"
        )
    varying = [i for i in range(counts.pop()) if len({int(n[i]) for n in numbers}) > 1]
    if not varying:
        raise ApmgsrnError(
            f"{files[0]}: the file names carry no step number that differs between them "
            f"({files[0].name}, {files[1].name}, ...); name the steps with their number (e.g. run_0010.vti)"
        )
    key = varying[0]
    numbered = sorted(((int(n[key]), path) for n, path in zip(numbers, files)), key=lambda item: item[0])
    for (a, path_a), (b, path_b) in zip(numbered, numbered[1:]):
        if a == b:
            raise ApmgsrnError(f"{path_b}: has the step number {b} of {path_a.name} too; give each step once")
    stride = min(b - a for (a, _), (b, _) in zip(numbered, numbered[1:]))
    for (a, path_a), (b, path_b) in zip(numbered, numbered[1:]):
        if b - a != stride:
            missing = a + stride
            raise ApmgsrnError(
                f"{path_b}: step {b} follows step {a} ({path_a.name}) but the series steps by {stride}: step "
                f"{missing} is missing; add it, or train the parts before and after the gap separately"
            )
    return numbered


def _pvd_steps(path: Path) -> tuple[list[SeriesStep], list[float]]:
    """The data sets of a ParaView collection in timestep order (``<DataSet timestep= file=>``)."""
    import xml.etree.ElementTree as ElementTree

    if not path.exists():
        raise ApmgsrnError(f"{path}: no such file; check the path")
    text = read_regular(path, LIMITS.pvd_bytes)  # a regular file only (never a pipe), bounded
    # A collection needs no document type; refusing one keeps entity expansion (billion laughs) out.
    if b"<!DOCTYPE" in text or b"<!ENTITY" in text:
        raise ApmgsrnError(f"{path}: a .pvd collection must not declare a DOCTYPE or entities; is it damaged?")
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as exc:
        raise ApmgsrnError(f"{path}: not a readable .pvd collection ({exc}); check the XML") from None
    if root.tag != "VTKFile" or root.get("type") != "Collection":
        raise ApmgsrnError(f"{path}: not a ParaView collection (expected <VTKFile type=\"Collection\">)")
    entries = []
    for element in root.iter("DataSet"):
        file, timestep, part = element.get("file"), element.get("timestep", "0"), element.get("part", "0")
        if not file:
            raise ApmgsrnError(f"{path}: a <DataSet> has no file attribute; the collection is damaged")
        if part not in ("", "0"):
            raise ApmgsrnError(f"{path}: data set {file} is part {part} of a multi-part step; only one part per "
                               "step is supported (merge the parts first)")
        try:
            value = float(timestep)
        except ValueError:
            raise ApmgsrnError(f"{path}: timestep {timestep!r} of {file} is not a number") from None
        entries.append((value, (path.parent / file) if not Path(file).is_absolute() else Path(file)))
    if not entries:
        raise ApmgsrnError(f"{path}: the collection lists no <DataSet>; nothing to read")
    entries.sort(key=lambda item: item[0])
    for (a, file_a), (b, file_b) in zip(entries, entries[1:]):
        if a == b:
            raise ApmgsrnError(f"{path}: {file_b.name} and {file_a.name} share timestep {b:g}; give each step once")
    for _, file in entries:
        if not file.exists():
            raise ApmgsrnError(f"{path}: lists {file}, which does not exist; check the collection's folder")
        if not file.is_dir():  # a Zarr store is walked by its reader
            check_regular(file, container=path, role="its entry")
    return [SeriesStep(file) for _, file in entries], [value for value, _ in entries]


def series_fingerprint(series: VolumeSeries) -> dict:
    """A JSON-able identity of every step of a series (:func:`volume_fingerprint` of each, in order).

    Returns:
        ``{"steps": [fingerprint of step 0, ...]}``.
    """
    steps = []
    for index in range(len(series)):
        with series.volume(index) as volume:
            steps.append(volume_fingerprint(volume))
    return {"steps": steps}
