"""``bench compress``: the networks against SZ3, ZFP, SPERR and TTHRESH on one volume.

For each compressor setting (an error bound, bit planes for ZFP's fixed-precision mode, bits per value for
SPERR's fixed-rate mode, a PSNR target for TTHRESH), or, with ``ratios``, at each asked ratio (the setting
found by :func:`~apmgsrn.bench.compressors.match_ratio`), and for each network: compressed size and ratio,
PSNR and largest error over every voxel, compression time (training time for a network), whole-volume decompression time
and throughput, and the cost of answering random point queries. A compressor has to decompress the whole
volume before it can interpolate at a single point; a network evaluates the points directly.

Networks are trained through ``bench quality`` into the same folder (so ``quality.csv`` keeps them and a
second run reuses them), or given as existing model files.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from apmgsrn.api import load
from apmgsrn.arguments import MAX_BATCH_SIZE, check_choice, check_int, check_number
from apmgsrn.atomic import atomic_write_text
from apmgsrn.bench.charts import rate_distortion_chart
from apmgsrn.bench.compressors import RATIO_TOLERANCE, CodecFailed, RatioNotReached, get_compressor, match_ratio
from apmgsrn.bench.datasets import DataSpec, open_spec
from apmgsrn.bench.quality import QualityPlan, prepare_folder, run_quality
from apmgsrn.bench.results import CompressRow, write_rows
from apmgsrn.bench.tables import compress_table
from apmgsrn.choices import COMPRESSORS, MODEL_KINDS, PAPER_MODELS, SIZE_PRESETS
from apmgsrn.inference.decode import decode_array
from apmgsrn.inference.evaluate import check_volume_shape, compare_arrays
from apmgsrn.inference.query import query
from apmgsrn.ops.trilinear import sample_volume
from apmgsrn.recipes import MODELS


@dataclass(frozen=True)
class CompressPlan:
    """What ``bench compress`` runs.

    Attributes:
        dataset: the volume.
        models, sizes: networks to train (through ``bench quality``) when ``model_files`` is empty (no models
            and no files: the compressors alone).
        model_files: trained models of this volume to use instead.
        compressors: names of :data:`apmgsrn.bench.compressors.COMPRESSORS`.
        bounds: error bounds relative to the value range, one run per error-bounded compressor and bound.
        precisions: bit planes, one run per fixed-precision compressor (``zfp-precision``) and precision.
        rates: bits per value, one run per fixed-rate compressor (``sperr``) and rate.
        psnrs: target PSNRs (dB), one run per PSNR-targeting compressor (``tthresh``) and target.
        ratios: compression ratios (the volume's stored bytes / compressed bytes); when given, every compressor
            runs at each of them instead of the settings above, its setting searched by
            :func:`~apmgsrn.bench.compressors.match_ratio`; a ratio it cannot reach is skipped with the reason.
        ratio_tolerance: how near (relative) the search for a ratio aims; when no setting lands that near, the
            nearest one tried is kept if within :data:`~apmgsrn.bench.compressors.RATIO_ACCEPT` (5 %).
        iterations, batch_size, seed: training budget of the networks.
        query_points: random points of the query test.
    """

    dataset: DataSpec
    models: tuple[str, ...] = PAPER_MODELS
    sizes: tuple[str, ...] = ("small",)
    model_files: tuple[Path, ...] = ()
    compressors: tuple[str, ...] = COMPRESSORS
    bounds: tuple[float, ...] = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4)
    precisions: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 8)  # ZFP's fixed-precision bit planes: about 200:1 to 20-40:1
    rates: tuple[float, ...] = (2.0, 1.0, 0.3, 0.1, 0.03, 0.01, 0.003)  # SPERR: 16:1 to 10,000:1 of float32
    psnrs: tuple[float, ...] = (80.0, 70.0, 60.0, 50.0, 40.0, 30.0)  # TTHRESH targets, dB
    ratios: tuple[float, ...] = ()
    ratio_tolerance: float = RATIO_TOLERANCE
    iterations: int = 2000
    batch_size: int = 32768
    seed: int = 0
    query_points: int = 2**20

    def __post_init__(self) -> None:
        for model in self.models:
            check_choice("models", model, MODEL_KINDS)
        for size in self.sizes:
            check_choice("sizes", size, SIZE_PRESETS)
        for name in self.compressors:
            check_choice("compressors", name, COMPRESSORS)
        for bound in self.bounds:
            check_number("bounds", bound, 0.0, 1.0, low_open=True, high_open=True)
        for precision in self.precisions:
            check_int("precisions", precision, 1, 32)
        for rate in self.rates:
            check_number("rates", rate, 0.0, 64.0, low_open=True)
        for psnr in self.psnrs:
            check_number("psnrs", psnr, 0.0, 200.0, low_open=True)
        for ratio in self.ratios:
            check_number("ratios", ratio, 1.0, None, low_open=True)
        check_number("ratio_tolerance", self.ratio_tolerance, 0.0, 0.5, low_open=True)
        check_int("iterations", self.iterations, 1)
        check_int("batch_size", self.batch_size, 1, MAX_BATCH_SIZE)
        check_int("seed", self.seed, 0, 2**63 - 1)
        check_int("query_points", self.query_points, 1, MAX_BATCH_SIZE)


@dataclass(frozen=True)
class CompressReport:
    """Rows of one run and where they were written."""

    rows: list[CompressRow]
    skipped: list[str]
    csv: Path
    markdown: Path
    chart: Path


def compress_paths(out: Path, spec: DataSpec) -> dict[str, Path]:
    """Files of a compression benchmark of ``spec`` in folder ``out``."""
    return {
        "csv": out / f"compress_{spec.stem}.csv",
        "markdown": out / f"compress_{spec.stem}.md",
        "chart": out / f"compress_{spec.stem}.png",
    }


def run_compress(
    plan: CompressPlan, out: Path, device: torch.device, log: Callable[[str], None] = print
) -> CompressReport:
    """Run every compressor setting and network of ``plan``; write CSV, Markdown table and chart.

    Args:
        plan: the volume, compressors and networks.
        out: results folder (created if missing).
        device: where networks are trained and evaluated.
        log: receives one line per result and per skipped compressor.

    Returns:
        The rows (compressors first, then networks) and the skipped compressors' reasons.
    """
    prepare_folder(out)
    paths = compress_paths(Path(out), plan.dataset)
    volume = open_spec(plan.dataset)
    data = volume.to_numpy()  # [D, H, W] float32: compressors need the whole array
    label = plan.dataset.label
    generator = torch.Generator().manual_seed(1234)
    points = torch.rand(plan.query_points, 3, generator=generator) * 2 - 1  # [Q, 3]

    rows: list[CompressRow] = []
    skipped: list[str] = []
    for name in plan.compressors:
        compressor = get_compressor(name)
        if not compressor.available():
            skipped.append(compressor.unavailable_reason())
            log(f"skipped {compressor.unavailable_reason()}")
            continue
        for setting in _settings(plan, compressor, data, volume.stored_bytes, skipped, log):
            try:
                row = measure_compressor(compressor, data, setting, points, label, volume.stored_bytes)
            except CodecFailed as reason:
                skipped.append(f"{reason} (at {compressor.setting} {setting:g})")
                log(f"skipped {skipped[-1]}")
                continue
            rows.append(row)
            log(f"{label} {name} {compressor.setting} {setting:g}: ratio {row.compression_ratio:.1f}, "
                f"{row.psnr:.2f} dB")

    model_files = list(plan.model_files)
    settings = {}
    if not model_files and plan.models:
        quality = QualityPlan(
            datasets=(plan.dataset,), models=plan.models, sizes=plan.sizes, seeds=1,
            iterations=plan.iterations, batch_size=plan.batch_size,
        )
        trained = run_quality(quality, Path(out), device, log=log)
        for row in trained:
            if row.dataset == label and row.model in plan.models and row.size in plan.sizes and row.seed == 0 \
                    and row.iterations == plan.iterations and row.batch_size == plan.batch_size:
                model_files.append(Path(row.model_file))
                settings[str(row.model_file)] = (row.size, row.train_seconds)
    for path in model_files:
        size, seconds = settings.get(str(path), (None, None))
        row = measure_model(path, data, points, label, device, volume.stored_bytes, size, seconds)
        rows.append(row)
        log(f"{label} {row.method} {row.setting}: ratio {row.compression_ratio:.1f}, {row.psnr:.2f} dB")

    write_rows(paths["csv"], rows, CompressRow)
    atomic_write_text(paths["markdown"], compress_table(rows), "results table")
    if rows:
        rate_distortion_chart(rows, paths["chart"], title=f"{label} {volume_shape_text(volume)}")
    return CompressReport(rows, skipped, paths["csv"], paths["markdown"], paths["chart"])


def _settings(plan: CompressPlan, compressor, data: np.ndarray, data_bytes: int, skipped: list[str],
              log: Callable[[str], None]) -> list[float]:
    """The settings ``compressor`` runs at: the plan's list for its kind of setting, or, with ``plan.ratios``,
    the setting matched to each ratio (a ratio out of its reach goes to ``skipped``)."""
    if not plan.ratios:
        return list({"bound": plan.bounds, "precision": plan.precisions, "rate": plan.rates,
                     "psnr": plan.psnrs}[compressor.setting])
    settings = []
    for ratio in plan.ratios:
        try:
            match = match_ratio(compressor, data, ratio, data_bytes, plan.ratio_tolerance)
        except (RatioNotReached, CodecFailed) as reason:
            skipped.append(f"{reason}")
            log(f"skipped {reason}")
            continue
        settings.append(match.setting)
    return settings


def volume_shape_text(volume) -> str:
    return "x".join(str(n) for n in reversed(volume.shape))


def measure_compressor(compressor, data: np.ndarray, setting: float, points: torch.Tensor, label: str,
                       data_bytes: int) -> CompressRow:
    """Compress, decompress and query one volume with one compressor at one setting.

    Args:
        compressor: a :class:`~apmgsrn.bench.compressors.Compressor`.
        data: ``[D, H, W]`` float32 volume.
        setting: the compressor's setting (an error bound relative to the value range, or bit planes).
        points: ``[Q, 3]`` query points in ``[-1, 1]^3``.
        label: volume name for the row.
        data_bytes: the volume's size as stored (its own dtype), for the compression ratio.
    """
    start = time.perf_counter()
    compressed = compressor.compress(data, setting)
    compress_seconds = time.perf_counter() - start
    start = time.perf_counter()
    restored = compressor.decompress(compressed)
    decompress_seconds = time.perf_counter() - start
    errors = compare_arrays(restored, data)
    # Point queries from the compressed form: decompress everything, then interpolate.
    start = time.perf_counter()
    values = sample_volume(torch.from_numpy(compressor.decompress(compressed)), points)
    query_seconds = time.perf_counter() - start
    del values
    return CompressRow(
        dataset=label,
        method=compressor.name,
        setting=f"{setting:g}",
        compressed_bytes=len(compressed.data),
        compression_ratio=data_bytes / len(compressed.data),
        compression_ratio_float32=data.size * 4 / len(compressed.data),
        psnr=errors.psnr,
        max_abs_error=errors.max_abs_error,
        compress_seconds=compress_seconds,
        decompress_seconds=decompress_seconds,
        decompress_voxels_per_second=data.size / decompress_seconds,
        query_points=points.shape[0],
        query_seconds=query_seconds,
        query_points_per_second=points.shape[0] / query_seconds,
    )


def measure_model(
    path: Path,
    data: np.ndarray,
    points: torch.Tensor,
    label: str,
    device: torch.device,
    data_bytes: int,
    size: str | None = None,
    train_seconds: float | None = None,
) -> CompressRow:
    """Decode and query one trained model of ``data``'s volume.

    Args:
        path: model file.
        data: ``[D, H, W]`` float32 ground truth.
        points: ``[Q, 3]`` query points.
        label: volume name for the row.
        device: where to evaluate.
        data_bytes: the volume's size as stored (its own dtype), for the compression ratio.
        size: preset name for the row (else read from the file's training record, else ``custom``).
        train_seconds: training time (else read from the file).

    Raises:
        ApmgsrnError: the model was trained on a volume of another shape.
    """
    model = load(path, device=device)
    field, description = model.field, model.description
    check_volume_shape(data.shape, description.volume_shape, label)
    if train_seconds is None:
        train_seconds = float(description.training.get("seconds", math.nan))
    method = description.model
    if description.packing is not None:  # its own line in tables and charts
        method += " packed" + (" bounded" if description.packing.max_error is not None else "")
    query(field, points[:4096].to(device))  # warm-up: allocator, kernels, thread pool
    _synchronize(device)
    start = time.perf_counter()
    decoded = decode_array(field, data.shape)
    decompress_seconds = time.perf_counter() - start
    errors = compare_arrays(decoded, data)
    _synchronize(device)
    start = time.perf_counter()
    query(field, points)
    _synchronize(device)
    query_seconds = time.perf_counter() - start
    file_bytes = Path(path).stat().st_size
    return CompressRow(
        dataset=label,
        method=method,
        setting=size or _preset_of(description.config) or "custom",
        compressed_bytes=file_bytes,
        compression_ratio=data_bytes / file_bytes,
        compression_ratio_float32=data.size * 4 / file_bytes,
        psnr=errors.psnr,
        max_abs_error=errors.max_abs_error,
        compress_seconds=train_seconds,
        decompress_seconds=decompress_seconds,
        decompress_voxels_per_second=data.size / decompress_seconds,
        query_points=points.shape[0],
        query_seconds=query_seconds,
        query_points_per_second=points.shape[0] / query_seconds,
    )


def _preset_of(field_config) -> str | None:
    """The size preset whose encoder config a field config has, if any."""
    config = dataclasses.asdict(field_config.encoder)
    recipe = MODELS.get(field_config.model)
    for preset, fields in ({} if recipe is None else recipe.presets).items():
        if all(config.get(k) == (tuple(v) if isinstance(v, list) else v) for k, v in fields.items()):
            return preset
    return None


def _synchronize(device: torch.device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
