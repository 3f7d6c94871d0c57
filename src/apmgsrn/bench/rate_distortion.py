"""``bench rd``: the rate-distortion page, every method at the same ratios on volumes no compressor made.

For each volume and each asked ratio (against the volume as float32, 4 bytes a voxel, for every volume: a
uint8 volume's ratio against its stored bytes is a quarter of it), every compressor of
:mod:`apmgsrn.bench.compressors` at the setting :func:`~apmgsrn.bench.compressors.match_ratio` finds, and
each network kind trained by ``apmgsrn train --ratio`` (the command line itself, in a child process: the
model is sized and packed there, not here). Measured per point (:func:`~apmgsrn.bench.compress.measure_compressor`,
:func:`~apmgsrn.bench.compress.measure_model`): PSNR and largest error over every voxel, and the cost of random
access: a query of random points (a network evaluates them; a compressor decompresses the whole volume and
then interpolates) and a 64^3 region (a network decodes the region; a compressor decompresses the whole volume
and slices).

The points go to ``bench compress``'s results file of the volume (``OUT/compress_NAME.csv``, its rows and
format) and the networks to ``OUT/models``; ``OUT/rate_distortion_NAME.csv`` records which row answers which
asked ratio, with the region timing, and the ratios a compressor could not reach or failed at (with the
reason). A second run measures only what is missing, and trains nothing whose model file is there.

The page (:func:`rate_distortion_page`) holds per volume a PSNR / largest-error table, the crossover ratio of
each network kind with each compressor (:func:`crossovers`), a chart, the random-access table, and, written
from the numbers, where the classical compressors still win and by how much.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import subprocess
import sys
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
from apmgsrn.bench.compress import compress_paths, measure_compressor, measure_model
from apmgsrn.bench.compressors import (
    RATIO_ACCEPT,
    RATIO_TOLERANCE,
    CodecFailed,
    RatioNotReached,
    get_compressor,
    match_ratio,
)
from apmgsrn.bench.datasets import (
    BENCHMARK_VOLUMES,
    DataSpec,
    benchmark_volume,
    open_spec,
    parse_data_spec,
)
from apmgsrn.bench.quality import prepare_folder
from apmgsrn.bench.results import MODEL_TITLES, CompressRow, append_row, read_rows
from apmgsrn.bench.tables import COMPRESSOR_FAMILIES, compressor_curve
from apmgsrn.choices import COMPRESSORS, DEFAULT_MODEL, MODEL_KINDS
from apmgsrn.errors import ApmgsrnError

#: The ratios of the page, against float32 bytes: from where every compressor is near-lossless to where
#: only a few hundred bytes remain of a 128^3 volume.
RATIOS = (30.0, 100.0, 300.0, 1000.0, 3000.0, 10000.0)
#: ``--quick``: two ratios either side of where the networks and compressors trade places, and a short budget,
#: for iterating on the page and for the tests.
QUICK_RATIOS = (100.0, 1000.0)
QUICK_ITERATIONS = 200
#: The network kinds of the page: the default model and the paper's.
NETWORK_KINDS = tuple(dict.fromkeys((DEFAULT_MODEL, "apmgsrn")))
#: The volumes of the page when none is named: the registered volumes of 128^3 and more that no lossy
#: compressor produced (the turbulence is computed here on first use).
DEFAULT_VOLUMES = ("c60", "richtmyer-meshkov", "turbulence-vorticity-128")
#: How far from the asked ratio a compressor's nearest setting may land and still be kept (when none lands
#: within 5 %): ZFP's bit planes and SZ3's coarsest bounds move the ratio in steps of up to about 1.4x. The
#: table gives the ratio reached; comparisons at an asked ratio interpolate between reached ratios or take a
#: point within 5 % of it, never a farther one.
NEAREST_ACCEPT = 0.3
#: Random points of the query test, and the side of the decoded region.
QUERY_POINTS = 2**18
REGION_SIDE = 64


class NotMeasured(ApmgsrnError):
    """A point that could not be measured this time, and is tried again on the next run: a compressor's
    package missing, or ``apmgsrn train`` refusing or failing (its error line is the message)."""


@dataclass(frozen=True)
class RateDistortionPlan:
    """What ``bench rd`` runs.

    Attributes:
        datasets: the volumes.
        ratios: asked compression ratios, the volume's float32 bytes / compressed bytes.
        compressors: names of :data:`apmgsrn.bench.compressors.COMPRESSORS`.
        models: network kinds, each trained by ``apmgsrn train --model KIND --ratio R``.
        iterations, batch_size, seed: the networks' training budget.
        query_points: random points of the query test.
        region: side of the decoded region (each axis at most the volume's).
        ratio_tolerance: how near a compressor's ratio search aims (:func:`match_ratio`).
        compress_seconds: the longest one compression may take: a compressor slower than that on a volume is
            not measured there (its ratio search compresses up to 40 times), and tried again on the next run;
            None: no limit.
    """

    datasets: tuple[DataSpec, ...]
    ratios: tuple[float, ...] = RATIOS
    compressors: tuple[str, ...] = COMPRESSORS
    models: tuple[str, ...] = NETWORK_KINDS
    iterations: int = 2000
    batch_size: int = 32768
    seed: int = 0
    query_points: int = QUERY_POINTS
    region: int = REGION_SIDE
    ratio_tolerance: float = RATIO_TOLERANCE
    compress_seconds: float | None = None

    def __post_init__(self) -> None:
        if not self.datasets:
            raise ApmgsrnError("datasets: name at least one volume")
        if not self.ratios:
            raise ApmgsrnError("ratios: give at least one ratio", arguments=("ratios",))
        for ratio in self.ratios:
            check_number("ratios", ratio, 1.0, None, low_open=True)
        for name in self.compressors:
            check_choice("compressors", name, COMPRESSORS)
        for model in self.models:
            check_choice("models", model, MODEL_KINDS)
        check_int("iterations", self.iterations, 1)
        check_int("batch_size", self.batch_size, 1, MAX_BATCH_SIZE)
        check_int("seed", self.seed, 0, 2**63 - 1)
        check_int("query_points", self.query_points, 1, MAX_BATCH_SIZE)
        check_int("region", self.region, 1, 4096)
        check_number("ratio_tolerance", self.ratio_tolerance, 0.0, 0.5, low_open=True)
        if self.compress_seconds is not None:
            check_number("compress_seconds", self.compress_seconds, 0.0, None, low_open=True)


@dataclass(frozen=True)
class PointRow:
    """Which measured point answers one asked ratio of one method (``OUT/rate_distortion_NAME.csv``).

    Attributes:
        dataset: the volume's label.
        method: a compressor's name, or the network kind trained.
        ratio: the asked ratio, against float32.
        status: ``measured`` or ``skipped`` (a compressor that cannot reach the ratio or failed; a network that
            could not be trained is not recorded: the next run tries again).
        note: why it was skipped; a network's model file.
        row_method, row_setting, compressed_bytes: the row of ``compress_NAME.csv`` (method, setting, bytes).
        region_seconds: time to produce the region (a network decodes it; a compressor decompresses all, slices).
        region_voxels: voxels of the region.
    """

    dataset: str
    method: str
    ratio: float
    status: str
    note: str
    row_method: str = ""
    row_setting: str = ""
    compressed_bytes: int = 0
    region_seconds: float = math.nan
    region_voxels: int = 0


@dataclass(frozen=True)
class VolumeResult:
    """One volume's points: per method and asked ratio its :class:`CompressRow` (ratios in float32 terms:
    ``compression_ratio`` is the float32 ratio), its region time, or why it is missing."""

    label: str
    shape: str
    dtype: str
    stem: str
    ratios: tuple[float, ...]
    rows: dict[tuple[str, float], CompressRow]
    region_seconds: dict[tuple[str, float], float]
    missing: dict[tuple[str, float], str]
    methods: tuple[str, ...]
    region: str


@dataclass(frozen=True)
class RateDistortionReport:
    """The volumes measured, the page written and its charts."""

    volumes: list[VolumeResult]
    page: Path
    charts: list[Path]


def rd_paths(out: Path, spec: DataSpec) -> dict[str, Path]:
    """Files of the rate-distortion runs of ``spec`` in ``out``: ``bench compress``'s CSV, the point index."""
    return {"csv": compress_paths(out, spec)["csv"], "points": Path(out) / f"rate_distortion_{spec.stem}.csv"}


def page_path(out: str | os.PathLike, page: str | os.PathLike | None) -> Path:
    """The page ``--page`` names, else ``OUT/rate_distortion.md``."""
    return Path(page) if page is not None else Path(out) / "rate_distortion.md"


def pending_volume(text: str) -> bool:
    """True when ``text`` names a registered volume that :mod:`apmgsrn.bench.simulate` computes (the
    turbulence, the registry's generated volumes) and its file is not made yet (and no file of that name
    exists)."""
    if Path(text).exists():
        return False
    volume = next((v for v in BENCHMARK_VOLUMES if v.name == text), None)
    return volume is not None and volume.root == "generated" and not volume.path().exists()


def resolve_volume(text: str) -> DataSpec:
    """``PATH[:VARIABLE]`` or a registered volume's name; the registered turbulence may not be computed yet
    (:func:`ensure_volume` computes it when the run reaches it).

    Raises:
        ApmgsrnError: no such file or volume.
    """
    return benchmark_volume(text).spec() if pending_volume(text) else parse_data_spec(text)


def ensure_volume(spec: DataSpec, log: Callable[[str], None] = print) -> None:
    """Compute a registered generated volume (the turbulence) whose file is missing: the fixed run
    :data:`~apmgsrn.bench.simulate.BENCHMARK_RUN`, kept in ``.bench_data``; any other volume is left as it is."""
    volume = next((v for v in BENCHMARK_VOLUMES if v.root == "generated" and v.spec() == spec), None)
    if volume is not None and not spec.path.exists():
        from apmgsrn.bench.simulate import BENCHMARK_RUN, write_run

        log(f"computing {volume.name} ({volume.path()}): {volume.make}")
        write_run(BENCHMARK_RUN, volume.path().parent, log=log)


def run_rate_distortion(plan: RateDistortionPlan, out: Path, page: Path, device: torch.device,
                        log: Callable[[str], None] = print) -> RateDistortionReport:
    """Measure what ``out`` lacks of ``plan``, then write the page and its charts (beside it, in ``images/``).

    Args:
        plan: volumes, ratios, compressors, networks and budget.
        out: results folder (``bench compress``'s layout: CSVs, ``models/``).
        page: Markdown file to write; the charts go to ``page.parent / "images"``.
        device: where the networks are trained and evaluated.
        log: one line per point measured, reused or skipped.
    """
    out = Path(out)
    prepare_folder(out)
    volumes = [measure_volume(plan, spec, out, device, log) for spec in plan.datasets]
    images = Path(page).parent / "images"
    images.mkdir(parents=True, exist_ok=True)
    charts = []
    for result in volumes:
        rows = list(result.rows.values())
        chart = images / f"rate_distortion_{result.stem}.png"
        if rows:
            rate_distortion_chart(rows, chart, title=f"{result.label} {result.shape}",
                                  ratio_label="compression ratio (float32 bytes / compressed bytes)")
            charts.append(chart)
    command = bench_rd_command(plan, out, Path(page), device)
    atomic_write_text(page, rate_distortion_page(plan, volumes, command), "rate-distortion page")
    return RateDistortionReport(volumes, Path(page), charts)


def bench_rd_command(plan: RateDistortionPlan, out: Path, page: Path, device: torch.device) -> str:
    """The ``apmgsrn bench rd`` command line of ``plan`` (what the page says it was made by)."""
    data = " ".join(_data_text(spec) for spec in plan.datasets)
    return (f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '1')} apmgsrn bench rd {data} "
            f"--ratios {' '.join(f'{r:g}' for r in plan.ratios)} --models {' '.join(plan.models)} "
            f"--compressors {' '.join(plan.compressors)} --iterations {plan.iterations} "
            f"--batch-size {plan.batch_size} --seed {plan.seed} --query-points {plan.query_points} "
            f"--region {plan.region}"
            + (f" --compress-seconds {plan.compress_seconds:g}" if plan.compress_seconds is not None else "")
            + f" --device {device} --out {Path(out).as_posix()} --page {Path(page).as_posix()}")


def _data_text(spec: DataSpec) -> str:
    """How to name ``spec`` on the command line: a registered volume by its name, else ``PATH[:VARIABLE]``."""
    registered = next((volume.name for volume in BENCHMARK_VOLUMES if volume.spec() == spec), None)
    return registered or str(spec.path) + (f":{spec.variable}" if spec.variable else "")


def measure_volume(plan: RateDistortionPlan, spec: DataSpec, out: Path, device: torch.device,
                   log: Callable[[str], None]) -> VolumeResult:
    """Every method of ``plan`` at every ratio on ``spec``: reused from ``out`` where recorded, else measured
    and appended to the two CSVs as it finishes (a run that stops keeps what it finished)."""
    paths = rd_paths(out, spec)
    ensure_volume(spec, log)
    volume = open_spec(spec)
    data = volume.to_numpy()  # [D, H, W] float32
    float32_bytes = data.size * 4
    label = spec.label
    compress_rows = read_rows(paths["csv"], CompressRow)
    index = [p for p in read_rows(paths["points"], PointRow) if p.dataset == label]
    generator = torch.Generator().manual_seed(1234)
    points = torch.rand(plan.query_points, 3, generator=generator) * 2 - 1  # [Q, 3] in [-1, 1]^3
    region = region_box(data.shape, plan.region)

    rows, seconds, missing = {}, {}, {}
    too_slow: dict[str, str] = {}  # compressors over the time limit on this volume: their other ratios too
    methods = [*plan.compressors, *plan.models]
    for method in methods:
        is_network = method in plan.models
        for ratio in plan.ratios:
            key = (method, ratio)
            model_file = network_file(out, spec, method, ratio, plan) if is_network else None
            found = _recorded(index, compress_rows, label, method, ratio, model_file)
            if found is None and method in too_slow:
                missing[key] = too_slow[method]
                continue
            if isinstance(found, str):
                missing[key] = found
                log(f"{label} {method} {ratio:g}:1: skipped before, {found}")
                continue
            if found is None:
                try:
                    found = (_measure_network(spec, volume, data, method, ratio, model_file, points, region, plan,
                                              device, log) if is_network else
                             _measure_compressor(method, data, ratio, float32_bytes, volume.stored_bytes, points,
                                                 region, label, plan.ratio_tolerance, plan.compress_seconds))
                except (RatioNotReached, CodecFailed) as reason:
                    append_row(paths["points"], PointRow(label, method, ratio, "skipped", str(reason)))
                    missing[key] = str(reason)
                    log(f"{label} {method} {ratio:g}:1: skipped, {reason}")
                    continue
                except NotMeasured as reason:
                    missing[key] = str(reason)
                    if isinstance(reason, TooSlow):
                        too_slow[method] = str(reason)
                    log(f"{label} {method} {ratio:g}:1: not measured, {reason}")
                    continue
                row, point = found
                append_row(paths["csv"], row)
                append_row(paths["points"], point)
                compress_rows.append(row)
                log(f"{label} {row.method} at {ratio:g}:1: {row.compression_ratio_float32:,.1f}:1, "
                    f"{row.psnr:.2f} dB, region {point.region_seconds:.3f} s")
            else:
                row, point = found
                log(f"{label} {method} at {ratio:g}:1: reused ({row.psnr:.2f} dB)")
            if is_network and abs(row.compression_ratio_float32 / ratio - 1) > RATIO_ACCEPT:
                # a float32 model left where packing failed, or a file from other settings: not this point
                missing[key] = (f"{model_file} gives {row.compression_ratio_float32:,.4g}:1, not within "
                                f"{RATIO_ACCEPT:.0%} of {ratio:,.4g}:1 (delete it to train it again)")
                log(f"{label} {method} {ratio:g}:1: not measured, {missing[key]}")
                continue
            rows[key] = dataclasses.replace(row, compression_ratio=row.compression_ratio_float32)
            seconds[key] = point.region_seconds
    return VolumeResult(label, "x".join(str(n) for n in reversed(data.shape)), str(volume.dtype), spec.stem,
                        tuple(plan.ratios), rows, seconds, missing, tuple(methods),
                        "x".join(str(s.stop - s.start) for s in reversed(region)))


def _recorded(index: list[PointRow], compress_rows: list[CompressRow], label: str, method: str, ratio: float,
              model_file: Path | None) -> tuple[CompressRow, PointRow] | str | None:
    """What the CSVs hold for ``method`` at ``ratio``: the row and its index entry, the reason it was skipped,
    or None (measure it). A network's entry counts only for the same model file (budget and seed), and only
    while that file is there (deleted, it is trained again)."""
    if model_file is not None and not model_file.exists():
        return None
    for point in reversed(index):
        if point.method != method or not math.isclose(point.ratio, ratio):
            continue
        if model_file is not None and point.note != str(model_file):
            continue
        if point.status == "skipped":
            return point.note
        row = next((r for r in compress_rows if r.dataset == label and r.method == point.row_method
                    and r.setting == point.row_setting and r.compressed_bytes == point.compressed_bytes), None)
        if row is not None:
            return row, point
    return None


def region_box(shape: tuple[int, ...], side: int) -> tuple[slice, slice, slice]:
    """The centred region of ``side`` voxels a side (at most the volume's), as ``(z, y, x)`` slices."""
    starts = [(n - min(side, n)) // 2 for n in shape]
    return tuple(slice(start, start + min(side, n)) for start, n in zip(starts, shape))


def _measure_compressor(name: str, data: np.ndarray, ratio: float, float32_bytes: int, stored_bytes: int,
                        points: torch.Tensor, region: tuple[slice, ...], label: str, tolerance: float,
                        limit: float | None) -> tuple[CompressRow, PointRow]:
    compressor = get_compressor(name)
    if not compressor.available():
        raise NotMeasured(compressor.unavailable_reason())
    if limit is not None:
        compressor = _TimeLimited(compressor, limit)
    match = match_ratio(compressor, data, ratio, float32_bytes, tolerance, NEAREST_ACCEPT)
    row = measure_compressor(compressor, data, match.setting, points, label, stored_bytes)
    # A region from the compressed form: the whole volume decompressed, then the box cut out.
    timings = []
    for _ in range(2):  # the faster of two: the first may still pay for the codec's first use
        start = time.perf_counter()
        block = np.ascontiguousarray(compressor.decompress(match.compressed)[region])
        timings.append(time.perf_counter() - start)
    point = PointRow(label, name, ratio, "measured", f"{compressor.setting} {match.setting:g}", row.method,
                     row.setting, row.compressed_bytes, min(timings), int(block.size))
    return row, point


class TooSlow(NotMeasured):
    """One compression took longer than the run allows."""


@dataclass(frozen=True)
class _TimeLimited:
    """A compressor whose every compression raises :class:`TooSlow` once it took longer than ``limit`` s."""

    compressor: object
    limit: float

    def __getattr__(self, name: str):
        return getattr(self.compressor, name)

    def compress(self, volume: np.ndarray, setting: float):
        start = time.perf_counter()
        compressed = self.compressor.compress(volume, setting)
        took = time.perf_counter() - start
        if took > self.limit:
            raise TooSlow(f"{self.compressor.name}: one compression of this volume took {took:.0f} s, over the "
                          f"{self.limit:g} s this run allows (its ratio search compresses up to 40 times)")
        return compressed


def network_file(out: Path, spec: DataSpec, kind: str, ratio: float, plan: RateDistortionPlan) -> Path:
    """Where the model of ``kind`` at ``ratio`` (float32) lies: named by its budget and seed, so another budget
    trains anew."""
    return (Path(out) / "models" / f"rd_{spec.stem}_{kind}_r{ratio:g}_i{plan.iterations}_b{plan.batch_size}"
            f"_s{plan.seed}.apmgsrn")


def train_command(spec: DataSpec, kind: str, stored_ratio: float, out: Path, plan: RateDistortionPlan,
                  device: torch.device) -> list[str]:
    """The ``apmgsrn train`` command line of one network; ``--ratio`` is against the stored bytes, so a ratio
    against float32 is asked as ``ratio * stored / float32`` (a quarter of it for uint8)."""
    command = [sys.executable, "-m", "apmgsrn", "train", str(spec.path)]
    if spec.variable:
        command += ["--variable", spec.variable]
    return command + ["--model", kind, "--ratio", f"{stored_ratio:.10g}", "--iterations", str(plan.iterations),
                      "--batch-size", str(plan.batch_size), "--seed", str(plan.seed), "--device", str(device),
                      "--out", str(out)]


def failure_reason(stderr: str, stdout: str, returncode: int) -> str:
    """One line saying why a command failed: its ``error:`` line, else the last line it wrote on stderr (a
    traceback's exception), else on stdout, else its exit status."""
    said = [[line for line in text.splitlines() if line.strip()] for text in (stderr, stdout)]
    errors = [line for line in said[0] + said[1] if line.startswith("error:")]
    return (errors or said[0] or said[1] or [f"exit status {returncode}"])[-1].removeprefix("error: ")


def _measure_network(spec: DataSpec, volume, data: np.ndarray, kind: str, ratio: float, model_file: Path,
                     points: torch.Tensor, region: tuple[slice, ...], plan: RateDistortionPlan,
                     device: torch.device, log: Callable[[str], None]) -> tuple[CompressRow, PointRow]:
    if not model_file.exists():
        stored_ratio = ratio * volume.stored_bytes / (data.size * 4)
        command = train_command(spec, kind, stored_ratio, model_file, plan, device)
        log(f"training {kind} for {ratio:g}:1: {' '.join(command[2:])}")
        environment = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (
            str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH"))))}
        done = subprocess.run(command, capture_output=True, text=True, env=environment)
        if done.returncode != 0 or not model_file.exists():
            raise NotMeasured(f"training {kind} for {stored_ratio:.4g}:1 of the stored bytes failed: "
                              f"{failure_reason(done.stderr, done.stdout, done.returncode)}")
    row = measure_model(model_file, data, points, spec.label, device, volume.stored_bytes)
    model = load(model_file, device=device)
    z, y, x = region
    text = f"{x.start}:{x.stop},{y.start}:{y.stop},{z.start}:{z.stop}"  # x, y, z index ranges
    model.decode(region=text)  # warm-up: allocator, kernels, thread pool
    start = time.perf_counter()
    block = np.asarray(model.decode(region=text))
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - start
    point = PointRow(spec.label, kind, ratio, "measured", str(model_file), row.method, row.setting,
                     row.compressed_bytes, seconds, int(block.size))
    return row, point


# ---------------------------------------------------------------------------------------------------------------
# Crossovers and the page


@dataclass(frozen=True)
class Crossing:
    """Where two rate-distortion curves cross: the ratio, and which is ahead above it (``"network"`` or
    ``"compressor"``)."""

    ratio: float
    ahead_above: str


def crossovers(network: list[tuple[float, float]], compressor: list[tuple[float, float]]) -> list[Crossing]:
    """The ratios where the network's ``(ratio, PSNR)`` curve crosses the compressor's, by increasing ratio.

    Both curves are linear in log(ratio) between their points and compared over the ratios both span (every
    point of either there); a crossing between two such ratios is interpolated in log(ratio), and a meeting at
    the first or last of them is a crossing there (at the edge). Points without a finite PSNR are left out.
    """
    a = sorted((r, p) for r, p in network if math.isfinite(p) and r > 0)
    b = sorted((r, p) for r, p in compressor if math.isfinite(p) and r > 0)
    if not a or not b:
        return []
    low, high = max(a[0][0], b[0][0]), min(a[-1][0], b[-1][0])
    if low > high:
        return []
    ratios = sorted({r for r, _ in (*a, *b) if low <= r <= high} | {low, high})
    grid = [math.log(r) for r in ratios]
    gaps = [_at(a, x) - _at(b, x) for x in grid]  # network minus compressor, dB
    found: list[Crossing] = []
    for i, (x0, x1, d0, d1) in enumerate(zip(grid, grid[1:], gaps, gaps[1:])):
        if d0 == 0:
            if i == 0 and d1 != 0:  # meeting at the first ratio
                found.append(Crossing(ratios[0], "network" if d1 > 0 else "compressor"))
            continue
        if (d0 < 0 <= d1) or (d0 > 0 >= d1):
            ratio = ratios[i + 1] if d1 == 0 else math.exp(x0 + (x1 - x0) * d0 / (d0 - d1))
            found.append(Crossing(ratio, "network" if d0 < 0 else "compressor"))
    return found


def _at(curve: list[tuple[float, float]], x: float) -> float:
    """A sorted ``(ratio, PSNR)`` curve at log-ratio ``x`` (linear in log ratio; ``x`` within its span)."""
    return float(np.interp(x, [math.log(r) for r, _ in curve], [p for _, p in curve]))


def psnr_at(curve: list[tuple[float, float]], ratio: float) -> float | None:
    """A curve's PSNR at ``ratio``: infinite where a point within :data:`RATIO_ACCEPT` of it is exact;
    interpolated in log(ratio) inside the span of its finite points; else a point within ``RATIO_ACCEPT``
    (the best); else None."""
    near = [p for r, p in curve if not math.isnan(p) and abs(r / ratio - 1) <= RATIO_ACCEPT]
    if any(p == math.inf for p in near):
        return math.inf
    finite = sorted((r, p) for r, p in curve if math.isfinite(p))
    if finite and finite[0][0] <= ratio <= finite[-1][0]:
        return _at(finite, math.log(ratio))
    return max(near) if near else None


def crossover_text(network: list[tuple[float, float]], compressor: list[tuple[float, float]]) -> str:
    """One cell: where the network overtakes the compressor (or falls behind), or ``none in range`` and who
    leads there and by how much (the curves as :func:`crossovers` takes them)."""
    a = sorted((r, p) for r, p in network if math.isfinite(p))
    b = sorted((r, p) for r, p in compressor if math.isfinite(p))
    low, high = (max(a[0][0], b[0][0]), min(a[-1][0], b[-1][0])) if a and b else (1.0, 0.0)
    if low > high:
        return "not compared (no ratio both reached)"
    found = crossovers(a, b)
    if found:
        return "; ".join(f"{c.ratio:,.0f}:1 ({c.ahead_above} ahead above)" for c in found)
    gaps = [_at(a, math.log(r)) - _at(b, math.log(r)) for r in (low, high)]
    who = "network" if gaps[0] > 0 else "compressor"
    if low == high:
        return f"one ratio compared ({low:,.0f}:1): {who} ahead by {abs(gaps[0]):.1f} dB"
    return (f"none in range {low:,.0f}-{high:,.0f}:1: {who} ahead throughout ({abs(gaps[0]):.1f} dB at "
            f"{low:,.0f}:1, {abs(gaps[1]):.1f} dB at {high:,.0f}:1)")


def on_ratios(curve: list[tuple[float, float]], ratios: tuple[float, ...]) -> list[tuple[float, float]]:
    """``curve`` at the asked ``ratios`` (:func:`psnr_at`; the ratios it has no value at left out): the curves
    of the page, so that points that landed within a few per cent of one asked ratio meet there."""
    values = [(ratio, psnr_at(curve, ratio)) for ratio in ratios]
    return [(ratio, value) for ratio, value in values if value is not None]


def _title(method: str) -> str:
    """``apmgsrn`` -> ``APMGSRN``, ``sperr-pwe`` -> ``SPERR-PWE``: the name of a method or kind in the page."""
    if method in MODEL_TITLES:
        return MODEL_TITLES[method]
    return method.upper()


def _network_curve(result: VolumeResult, kind: str) -> list[tuple[float, float]]:
    return [(row.compression_ratio, row.psnr) for (method, _), row in result.rows.items() if method == kind]


def _best_network(result: VolumeResult, kinds: tuple[str, ...], ratio: float) -> tuple[str, float] | None:
    values = [(kind, psnr_at(_network_curve(result, kind), ratio)) for kind in kinds]
    values = [(kind, value) for kind, value in values if value is not None]
    return max(values, key=lambda kv: kv[1]) if values else None


def _family_at(result: VolumeResult, family: str, ratio: float) -> float | None:
    rows = [row for (method, _), row in result.rows.items() if method in COMPRESSOR_FAMILIES[family]]
    return psnr_at(compressor_curve(rows, COMPRESSOR_FAMILIES[family]), ratio) if rows else None


def classical_wins(result: VolumeResult, kinds: tuple[str, ...]) -> str:
    """Where each compressor beats every network on this volume and by how much, and from which ratio a
    network leads every compressor: one paragraph, from the measured curves."""
    compared = []  # (ratio, best network PSNR, {family: PSNR}) where a network and a compressor were measured
    for ratio in result.ratios:
        best = _best_network(result, kinds, ratio)
        families = {family: _family_at(result, family, ratio) for family in COMPRESSOR_FAMILIES}
        families = {family: value for family, value in families.items() if value is not None}
        if best is not None and families:
            compared.append((ratio, best[1], families))
    if not compared:
        return f"**{result.label}** ({result.shape}): no ratio with both a network and a compressor measured."
    sentences, never = [], []
    absent = [family for family in COMPRESSOR_FAMILIES if not any(family in values for _, _, values in compared)]
    for family in COMPRESSOR_FAMILIES:
        wins = [(ratio, values[family] - network) for ratio, network, values in compared
                if family in values and values[family] > network]
        if wins:
            margins = ", ".join(f"{ratio:,.0f}:1 " + (f"by {margin:.1f} dB" if math.isfinite(margin) else
                                                      "(it is exact there)") for ratio, margin in wins)
            sentences.append(f"{family} beats every network at {margins}")
        elif any(family in values for _, _, values in compared):
            never.append(family)
    lead_from = None
    for ratio, network, values in reversed(compared):
        if not all(network > value for value in values.values()):
            break
        lead_from = ratio
    text = f"**{result.label}** ({result.shape}): " + ("; ".join(sentences) if sentences else
                                                         "no compressor beats the best network at any ratio compared")
    if never and sentences:
        text += f"; {' and '.join(never)} never {'does' if len(never) == 1 else 'do'}"
    if absent:
        text += f"; {' and '.join(absent)} not compared here (no point at these ratios: see below)"
    highest = compared[-1][0]
    if lead_from is None:
        text += f". At the highest ratio compared ({highest:,.0f}:1) a compressor still leads"
    elif lead_from == compared[0][0]:
        text += f". A network leads every compressor at every ratio compared ({lead_from:,.0f}-{highest:,.0f}:1)"
    else:
        text += f". A network leads every compressor measured from {lead_from:,.0f}:1 up to {highest:,.0f}:1"
    return text + "."


def access_text(result: VolumeResult, kinds: tuple[str, ...]) -> str:
    """Which compressors answer a point query and produce a region faster than every network on this volume
    (medians over the ratios measured), and which slower: one sentence from the measured times."""
    def medians(method: str) -> tuple[float, float] | None:
        keys = [key for key in result.rows if key[0] == method]
        if not keys:
            return None
        return (float(np.median([result.rows[k].query_points_per_second for k in keys])),
                float(np.median([result.region_seconds[k] for k in keys])))

    networks = {kind: medians(kind) for kind in kinds if medians(kind) is not None}
    compressors = {method: medians(method) for method in result.methods
                   if method not in kinds and medians(method) is not None}
    if not networks or not compressors:
        return ""
    query = max(value[0] for value in networks.values())
    region = min(value[1] for value in networks.values())

    def split(index: int, better) -> str:
        faster = [f"{_title(m)} {v[index] / 1e6:.3g}" if index == 0 else f"{_title(m)} {v[index]:.3g} s"
                  for m, v in compressors.items() if better(v[index])]
        return ", ".join(faster) if faster else "none"

    return (f"Random access on {result.label}: a query of {next(iter(result.rows.values())).query_points:,} "
            f"random points runs at {query / 1e6:.3g} Mpoints/s on the fastest network; faster: "
            f"{split(0, lambda v: v > query)} (Mpoints/s), slower: {split(0, lambda v: v <= query)}. A "
            f"{result.region} region takes {region:.3g} s from the fastest network; faster: "
            f"{split(1, lambda v: v < region)}, slower: {split(1, lambda v: v >= region)} (medians over the ratios).")


def rate_distortion_page(plan: RateDistortionPlan, volumes: list[VolumeResult], command: str) -> str:
    """The Markdown page: how it was made (``command``), the headline, then per volume the tables, crossovers
    and chart."""
    kinds = plan.models
    ratios_text = ", ".join(f"{r:,.0f}" for r in plan.ratios)
    lines = [
        "# Rate distortion: networks against SZ3, ZFP, SPERR and TTHRESH, on volumes no compressor made", "",
        f"Made by `{command}`; the same command again measures only what its results folder lacks. Every "
        "figure and sentence below is written from the measured rows by `apmgsrn.bench.rate_distortion`.", "",
        f"Protocol: ratios {ratios_text}:1 against the volume as **float32** (4 bytes a voxel, for every volume: "
        "the values every method compresses; a uint8 volume's ratio against its stored bytes is a quarter). "
        f"Compressors: each at the setting that lands within {plan.ratio_tolerance:.0%} of the ratio by "
        f"bisection (`match_ratio`), else at the nearest one tried within {NEAREST_ACCEPT:.0%} (ZFP's bit planes "
        "move the ratio in steps; the table then gives the ratio reached, and comparisons at a ratio interpolate "
        f"between reached ratios or take a point within {RATIO_ACCEPT:.0%}); SZ3 and ZFP with value-range-relative bounds, ZFP also in fixed-precision mode, SPERR at "
        "a fixed rate and in point-wise error mode, TTHRESH at a target PSNR; each compressor's line on the "
        "chart and in the crossovers is its best mode at each ratio"
        + (f"; a compressor whose one compression of a volume takes over {plan.compress_seconds:g} s is left out "
           "on that volume (the reason is listed under it). " if plan.compress_seconds is not None else ". ") +
        f"Networks: `apmgsrn train DATA --model KIND --ratio R --iterations {plan.iterations} --batch-size "
        f"{plan.batch_size} --seed {plan.seed}` ({', '.join(_title(k) for k in kinds)}; `--ratio` is against the "
        "stored bytes, so R is the float32 ratio times stored/float32), sized and packed by the command, one "
        f"seed. Random access: {plan.query_points:,} uniformly random points (a network evaluates them; a "
        "compressor decompresses the whole volume, then interpolates trilinearly: points / (decompress + "
        f"sample)) and a centred {plan.region}^3 region (a network decodes it; a compressor decompresses the "
        "whole volume and slices it, the faster of two runs; a network: one run after a warm-up). "
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores visible, "
        f"{torch.get_num_threads()} torch thread(s), OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; "
        f"1-minute load average {os.getloadavg()[0]:.2f} when the page was written (timings from a shared "
        "machine: read them as orders of magnitude).",
        "",
        "## Where the classical compressors still win", "",
    ]
    for result in volumes:
        lines += [classical_wins(result, kinds), ""]
    access = [access_text(result, kinds) for result in volumes]
    lines += [text + "\n" for text in access if text]
    lines += ["Best network against the best compressor at each ratio (PSNR dB; margin: network minus compressor):",
              "", "| volume | " + " | ".join(f"{r:,.0f}:1" for r in plan.ratios) + " |",
              "|---|" + "---|" * len(plan.ratios)]
    for result in volumes:
        cells = []
        for ratio in plan.ratios:
            best = _best_network(result, kinds, ratio)
            classical = [(family, _family_at(result, family, ratio)) for family in COMPRESSOR_FAMILIES]
            classical = [(family, value) for family, value in classical if value is not None]
            top = max(classical, key=lambda kv: kv[1]) if classical else None
            if best is None or top is None:
                cells.append("–")
                continue
            cells.append(f"{_title(best[0])} {best[1]:.2f} vs {top[0]} {top[1]:.2f} ({best[1] - top[1]:+.2f})")
        lines.append(f"| {result.label} | " + " | ".join(cells) + " |")
    lines.append("")
    for result in volumes:
        lines += volume_section(result, kinds)
    return "\n".join(lines) + "\n"


def volume_section(result: VolumeResult, kinds: tuple[str, ...]) -> list[str]:
    """One volume's tables, crossovers, chart and random-access costs."""
    ratios = result.ratios
    lines = [f"## {result.label} ({result.shape}, {result.dtype})", ""]
    if result.rows:
        lines += [f"![PSNR against ratio, {result.label}](images/rate_distortion_{result.stem}.png)", ""]
    lines += ["PSNR dB / largest error (data units) at each ratio; the ratio reached in parentheses where it is "
              "more than 2 % off; – not measured (reasons below).", "",
              "| method | " + " | ".join(f"{r:,.0f}:1" for r in ratios) + " |", "|---|" + "---|" * len(ratios)]
    notes = []
    for method in result.methods:
        cells = []
        for ratio in ratios:
            row = result.rows.get((method, ratio))
            if row is None:
                cells.append("–")
                reason = result.missing.get((method, ratio))
                if reason:
                    notes.append(f"- {_title(method)} at {ratio:,.0f}:1: {reason}")
                continue
            cell = f"{row.psnr:.2f} / {row.max_abs_error:.3g}"
            if abs(row.compression_ratio / ratio - 1) > 0.02:
                cell += f" ({row.compression_ratio:,.0f}:1)"
            cells.append(cell)
        lines.append(f"| {_title(method)} | " + " | ".join(cells) + " |")
    if notes:
        lines += ["", "Not measured:", "", *notes]

    lines += ["", "Crossover of each network with each compressor (its best mode at each ratio), interpolated in "
              "log(ratio):", "", "| network | " + " | ".join(COMPRESSOR_FAMILIES) + " |",
              "|---|" + "---|" * len(COMPRESSOR_FAMILIES)]
    for kind in kinds:
        curve = _network_curve(result, kind)
        cells = []
        for family, methods in COMPRESSOR_FAMILIES.items():
            rows = [row for (method, _), row in result.rows.items() if method in methods]
            other = on_ratios(compressor_curve(rows, methods), ratios) if rows else []
            cells.append(crossover_text(on_ratios(curve, ratios), other) if other and curve else "–")
        lines.append(f"| {_title(kind)} | " + " | ".join(cells) + " |")

    lines += ["", f"Random access: points/s of a query of {next(iter(result.rows.values())).query_points:,} "
              f"random points, and the time to produce a {result.region} region, median over the ratios measured "
              "(range in parentheses); whole-volume decompression (decode for a network) for reference.", "",
              "| method | query Mpoints/s | region s | whole volume s |", "|---|---|---|---|"] if result.rows else []
    for method in result.methods if result.rows else ():
        keys = [(method, r) for r in ratios if (method, r) in result.rows]
        if not keys:
            continue
        query = [result.rows[k].query_points_per_second / 1e6 for k in keys]
        region = [result.region_seconds[k] for k in keys]
        whole = [result.rows[k].decompress_seconds for k in keys]
        lines.append(f"| {_title(method)} | {_spread(query, '.3g')} | {_spread(region, '.3g')} | "
                     f"{_spread(whole, '.3g')} |")
    return lines + [""]


def _spread(values: list[float], spec: str) -> str:
    middle = float(np.median(values))
    if len(values) == 1:
        return format(middle, spec)
    return f"{format(middle, spec)} ({format(min(values), spec)}-{format(max(values), spec)})"
