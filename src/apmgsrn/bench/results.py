"""Benchmark result rows and their CSV files (one row per run; appended as runs finish)."""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from apmgsrn.atomic import atomic_write
from apmgsrn.errors import ApmgsrnError

#: Model names as the paper prints them.
MODEL_TITLES = {"apmgsrn": "APMGSRN", "fvsrn": "fVSRN", "ngp": "NGP", "hybrid": "hybrid"}
SIZE_ORDER = ("small", "medium", "large")


@dataclass(frozen=True)
class QualityRow:
    """One trained model of ``bench quality``.

    Attributes:
        dataset: ``file:variable`` label.
        shape: ``XxYxZ`` of the volume.
        model, size, seed: what was trained.
        iterations, batch_size, lr_schedule: how.
        parameters: real parameter count.
        parameter_bytes: the parameters' bytes in the dtypes the model file stores them in.
        file_bytes: size of the saved model file (weights + metadata).
        data_dtype: the volume's stored data type.
        data_bytes: the volume as stored, in its own dtype (a uint8 volume is 1 byte a voxel).
        compression_ratio: ``data_bytes / file_bytes`` (docs/method.md §8).
        compression_ratio_float32: the volume as float32 (4 bytes a voxel) / ``file_bytes``.
        psnr: over every voxel (dB).
        train_seconds: training loop wall time.
        ms_per_iteration: ``train_seconds`` per iteration.
        device: where it trained.
        model_file: path of the model file.
        voxel_fraction: share of every batch drawn on voxels (:class:`~apmgsrn.training.trainer.TrainConfig`;
            0 in files written before the option).
        max_abs_error: largest voxel error in data units (NaN in files written before the column).
        error_sampling: share of the voxel points drawn where the model was wrong (0 in files written before the
            option).
    """

    dataset: str
    shape: str
    model: str
    size: str
    seed: int
    iterations: int
    batch_size: int
    lr_schedule: str
    parameters: int
    parameter_bytes: int
    file_bytes: int
    data_dtype: str
    data_bytes: int
    compression_ratio: float
    compression_ratio_float32: float
    psnr: float
    train_seconds: float
    ms_per_iteration: float
    device: str
    model_file: str
    voxel_fraction: float = 0.0
    max_abs_error: float = math.nan
    error_sampling: float = 0.0

    def key(self) -> tuple:
        """What identifies a run: a row with the same key is not run again."""
        return (self.dataset, self.model, self.size, self.seed, self.iterations, self.batch_size, self.lr_schedule,
                self.voxel_fraction, self.error_sampling)


@dataclass(frozen=True)
class CompressRow:
    """One point of ``bench compress``: a compressor at one error bound, or one network.

    Attributes:
        dataset: ``file:variable`` label.
        method: ``sz3``, ``zfp`` or a model name.
        setting: the error bound relative to the value range (compressors) or the size preset (models).
        compressed_bytes: compressed stream or model file size.
        compression_ratio: the volume's stored bytes (its own dtype) / ``compressed_bytes`` (docs/method.md §8).
        compression_ratio_float32: the volume as float32 / ``compressed_bytes`` (what the compressors were
            given: every method compresses the float32 values).
        psnr: over every voxel (dB).
        max_abs_error: largest voxel error (data units).
        compress_seconds: compression time (training time for a network).
        decompress_seconds: whole-volume decompression (decode for a network).
        decompress_voxels_per_second: voxels / ``decompress_seconds``.
        query_points: random points of the query test.
        query_seconds: time to answer them from the compressed form (a compressor decompresses first).
        query_points_per_second: ``query_points / query_seconds``.
    """

    dataset: str
    method: str
    setting: str
    compressed_bytes: int
    compression_ratio: float
    compression_ratio_float32: float
    psnr: float
    max_abs_error: float
    compress_seconds: float
    decompress_seconds: float
    decompress_voxels_per_second: float
    query_points: int
    query_seconds: float
    query_points_per_second: float


@dataclass(frozen=True)
class SeriesStepRow:
    """One step of ``bench series`` (:mod:`apmgsrn.bench.series`): the series model's figures on it, or its own
    model's.

    Attributes:
        dataset: the series (:meth:`~apmgsrn.series.data.VolumeSeries.describe`).
        model, preset, seed, iterations, batch_size: what was trained (the series' start model's budget).
        method: ``series`` or ``own``.
        step: the step's index in the series.
        file: its file (and time index).
        psnr: over every voxel of the step (dB).
        psnr_between: between the voxels (:func:`~apmgsrn.bench.series.between_psnr`, dB).
        max_abs_error: largest voxel error in data units.
        file_bytes: the model file (the series' whole file on every one of its rows).
        train_seconds: the model's training time (the whole series' on every one of its rows).
        threads: torch's CPU threads.
        load_average: the machine's 1-minute load average when the row was written.
        cpu: the processor.
        model_file: path of the model file.
    """

    dataset: str
    model: str
    preset: str
    seed: int
    iterations: int
    batch_size: int
    method: str
    step: int
    file: str
    psnr: float
    psnr_between: float
    max_abs_error: float
    file_bytes: int
    train_seconds: float
    threads: int
    load_average: float
    cpu: str
    model_file: str


Row = TypeVar("Row", QualityRow, CompressRow, SeriesStepRow)


def write_rows(path: Path, rows: list, row_type: type) -> None:
    """Write ``rows`` (of ``row_type``) as a CSV with a header, replacing ``path`` atomically."""
    names = [f.name for f in dataclasses.fields(row_type)]
    text = io.StringIO(newline="")
    writer = csv.writer(text)
    writer.writerow(names)
    for row in rows:
        writer.writerow([_format(getattr(row, name)) for name in names])
    atomic_write(path, lambda temp: Path(temp).write_text(text.getvalue(), newline=""), "results file")


def append_row(path: Path, row) -> None:
    """Append one row to a CSV (header first if the file is new), so finished runs survive a crash."""
    names = [f.name for f in dataclasses.fields(type(row))]
    new = not path.exists() or path.stat().st_size == 0
    with open(path, "a", newline="") as handle:
        writer = csv.writer(handle)
        if new:
            writer.writerow(names)
        writer.writerow([_format(getattr(row, name)) for name in names])


def read_rows(path: Path, row_type: type[Row]) -> list[Row]:
    """Rows of a CSV written by :func:`write_rows` / :func:`append_row`; an absent file gives none.

    A file of an older version may lack the columns added since with a default (they take it).

    Raises:
        ApmgsrnError: the file is not such a CSV (another header).
    """
    if not path.exists():
        return []
    fields = {f.name: f.type for f in dataclasses.fields(row_type)}
    optional = {f.name for f in dataclasses.fields(row_type) if f.default is not dataclasses.MISSING}
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        if reader.fieldnames is None:
            return []
        if not set(fields) - optional <= set(reader.fieldnames) <= set(fields):
            raise ApmgsrnError(
                f"{path}: not a {row_type.__name__} results file of this version (other columns); move it away or "
                "pass another out= folder", arguments=("out",)
            )
        rows = []
        for record in reader:
            values = {}
            for name, kind in fields.items():
                if name not in record:
                    continue  # an older file: the field's default
                text = record[name]
                if kind in ("int", int):
                    values[name] = int(text)
                elif kind in ("float", float):
                    values[name] = float(text)
                else:
                    values[name] = text
            rows.append(row_type(**values))
    return rows


def _format(value) -> str:
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return str(value)


@dataclass(frozen=True)
class Summary:
    """Mean and spread of one quantity over seeds."""

    mean: float
    std: float
    count: int

    @staticmethod
    def of(values: list[float]) -> "Summary":
        finite = [v for v in values if math.isfinite(v)]
        if not finite:
            return Summary(math.nan, math.nan, len(values))
        std = statistics.stdev(finite) if len(finite) > 1 else 0.0
        return Summary(statistics.fmean(finite), std, len(values))


def group_quality(rows: list[QualityRow]) -> dict[tuple[str, str, str], list[QualityRow]]:
    """Rows by (dataset, model, size), in first-seen order."""
    groups: dict[tuple[str, str, str], list[QualityRow]] = {}
    for row in rows:
        groups.setdefault((row.dataset, row.model, row.size), []).append(row)
    return groups


def ordered(values, order) -> list:
    """Distinct ``values`` sorted by their place in ``order`` (unknown ones last, as first seen)."""
    seen = list(dict.fromkeys(values))
    rank = {v: i for i, v in enumerate(order)}
    return sorted(seen, key=lambda v: (rank.get(v, len(order)), seen.index(v)))
