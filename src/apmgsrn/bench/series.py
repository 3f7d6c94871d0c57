"""``bench series``: one model for a whole time series against one model per step, on any series.

The series criteria (docs/time_series.md), measured on a series ``apmgsrn train`` reads (several files, a glob,
a ``.pvd``, or one file with a time dimension):

1. **The series model**, trained exactly as ``apmgsrn train`` and :func:`apmgsrn.fit` train a series by default
   (:func:`apmgsrn.plan`: stepwise, packed within the recipe's size), kept as a model file.
2. **Own models**: an independent model of each measured step (:func:`measured_steps`: by default seven steps
   evenly spaced, the first and last among them), trained on that step alone with the same budget, preset and
   seed; trained after the series, on the same machine, so their training time is the one-step time the series
   is compared with.
3. **The report**: ``OUT/series.md`` (the criteria, then every measured step, over the voxels and between them)
   and ``OUT/series.png`` (PSNR over time of both).

With several seeds (``seeds``) both are trained once per seed, seed after seed; the criteria compare the means
over the seeds (one model's PSNR on a close-fitting step spreads by up to a dB between seeds, or between runs
whose data differ in the last bit), and the report says on how many seeds each step's series was at least that
seed's own model.

Rows go to ``OUT/series.csv`` as they finish. A rerun skips what is there: a series interrupted while it trained
resumes from its checkpoint, and own models already trained are not trained again.
"""

from __future__ import annotations

import math
import os
import platform
import statistics
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from apmgsrn.api import load
from apmgsrn.api import plan as resolve_plan
from apmgsrn.planning import Plan, volume_configs
from apmgsrn.options import TrainOptions
from apmgsrn.arguments import MAX_BATCH_SIZE, check_choice, check_int
from apmgsrn.atomic import atomic_write_text
from apmgsrn.bench.charts import psnr_over_time_chart
from apmgsrn.bench.quality import prepare_folder
from apmgsrn.bench.results import SeriesStepRow, append_row, read_rows
from apmgsrn.choices import MODEL_KINDS, SIZE_PRESETS
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.evaluate import psnr_from_mse
from apmgsrn.inference.query import query
from apmgsrn.ops.trilinear import sample_volume
from apmgsrn.training.fit import fit_volume
from apmgsrn.series.fit import fit_series

#: The criteria's bounds: the series file within this many own-model files, its training within this many
#: times one step's.
FILE_BOUND, TIME_BOUND = 5, 5
SERIES, OWN = "series", "own"


@dataclass(frozen=True)
class SeriesPlan:
    """What ``bench series`` measures.

    Attributes:
        data: the series, as :func:`apmgsrn.fit` takes it (files, a glob, a ``.pvd``, or one file with ``time``).
        variable, time, shape, dtype, fill_nonfinite: how to read it (as
            :func:`apmgsrn.series.data.open_series`).
        model, preset: the model kind (None: the default) and size preset of the series and the own models.
        iterations, batch_size: the budget of an own model, and of the series' start model.
        seeds: every model is trained with seeds ``0 .. seeds - 1``.
        steps: the steps measured against their own models (None: :func:`measured_steps`).
        between_points: points at which :func:`between_psnr` measures a model between the voxels.
    """

    data: tuple[str, ...]
    variable: str | None = None
    time: object = None
    shape: tuple[int, int, int] | None = None
    dtype: str | None = None
    fill_nonfinite: float | None = None
    model: str | None = None
    preset: str = "small"
    iterations: int = 2000
    batch_size: int = 32768
    seeds: int = 1
    steps: tuple[int, ...] | None = None
    between_points: int = 1 << 18

    def __post_init__(self) -> None:
        if self.model is not None:
            check_choice("model", self.model, MODEL_KINDS)
        check_choice("preset", self.preset, SIZE_PRESETS)
        check_int("iterations", self.iterations, 1)
        check_int("batch_size", self.batch_size, 1, MAX_BATCH_SIZE)
        check_int("seeds", self.seeds, 1)


def measured_steps(count: int, wanted: int = 7) -> list[int]:
    """``wanted`` step indices of ``count`` spread evenly, the first and the last among them (all of a shorter
    series)."""
    if count <= wanted:
        return list(range(count))
    return sorted({round(i * (count - 1) / (wanted - 1)) for i in range(wanted)})


def series_bench_paths(out: Path) -> dict[str, Path]:
    """Files of a series benchmark in folder ``out``."""
    return {"csv": out / "series.csv", "markdown": out / "series.md", "chart": out / "series.png",
            "models": out / "models"}


def between_psnr(field: Callable[[torch.Tensor], torch.Tensor], volume: np.ndarray, step: int,
                 points: int = SeriesPlan.between_points) -> float:
    """PSNR of a network between the voxels: at ``points`` points drawn uniformly in the domain (seeded by
    ``step``, so the same for every model of that step) against the data's trilinear interpolation there, what a
    renderer that interpolates the data samples; over the step's value range, as the PSNR over the voxels.

    Args:
        field: ``[N, 3]`` ``(x, y, z)`` points in ``[-1, 1]`` to values in data units.
        volume: ``[D, H, W]`` the step's values.
        step: the step's index.
        points: how many points.
    """
    generator = torch.Generator().manual_seed(1000 + step)
    where = torch.rand(points, 3, generator=generator) * 2 - 1  # [N, 3] (x, y, z)
    target = sample_volume(torch.from_numpy(np.ascontiguousarray(volume, dtype=np.float32)), where)  # [N]
    prediction = query(field, where).view(-1)
    mse = float((prediction.double() - target.double()).square().mean())
    return psnr_from_mse(mse, float(volume.max()) - float(volume.min()))


def run_series_bench(plan: SeriesPlan, out: Path, device: torch.device, log: Callable[[str], None] = print,
                     progress: bool = True) -> list[SeriesStepRow]:
    """Train what ``plan`` asks that ``out/series.csv`` does not hold yet; then write the report and the chart.

    Args:
        plan: the series, the steps measured, the budget and the seeds.
        out: results folder (created if missing; its parent must exist).
        device: training device.
        log: receives one line per model.
        progress: show the series' training progress.

    Returns:
        The rows of this plan (seed by seed: the series' every step, then the own models of the measured steps).

    Raises:
        ApmgsrnError: unreadable data, a step outside the series, an invalid option, another version's CSV.
    """
    setup = resolve_plan(list(plan.data), preset=plan.preset, model=plan.model, iterations=plan.iterations,
                         batch_size=plan.batch_size, device=str(device), variable=plan.variable, time=plan.time,
                         fill_nonfinite=plan.fill_nonfinite, shape=plan.shape, dtype=plan.dtype)
    if setup.input != "series":
        raise ApmgsrnError(f"{plan.data[0]}: one volume; bench series compares a series with its steps' own models")
    steps = list(plan.steps) if plan.steps is not None else measured_steps(len(setup.source))
    outside = [t for t in steps if not 0 <= t < len(setup.source)]
    if outside:
        raise ApmgsrnError(f"step {outside[0]} is not in the series: it has steps 0 .. {len(setup.source) - 1}",
                           arguments=("steps",))
    prepare_folder(out)
    paths = series_bench_paths(Path(out))
    rows: list[SeriesStepRow] = []
    for seed in range(plan.seeds):  # the seed sets only the training (the series and its packing are the same)
        seeded = replace(setup, training=replace(setup.training, seed=seed))
        label = f"seed {seed}: " if plan.seeds > 1 else ""
        rows += _run_seed(plan, seeded, seed, steps, paths, device, lambda line, label=label: log(label + line),
                          progress)
    atomic_write_text(paths["markdown"], series_report(rows, paths["chart"].name, plan.between_points),
                      "results table")
    series_chart(rows, paths["chart"])
    return rows


def _run_seed(plan: SeriesPlan, setup: Plan, seed: int, steps: list[int], paths: dict[str, Path],
              device: torch.device, log: Callable[[str], None], progress: bool) -> list[SeriesStepRow]:
    """The rows of one seed: those ``paths["csv"]`` holds, the missing ones trained and appended."""
    series = setup.source
    model = setup.field.field.model
    dataset = series.describe()
    rows = [r for r in read_rows(paths["csv"], SeriesStepRow) if r.dataset == dataset and r.model == model
            and (r.preset, r.seed, r.iterations, r.batch_size) == (plan.preset, seed, plan.iterations,
                                                                   plan.batch_size)]
    tag = f"{model}_{plan.preset}_s{seed}_i{plan.iterations}_b{plan.batch_size}"
    common = {"dataset": dataset, "model": model, "preset": plan.preset, "seed": seed,
              "iterations": plan.iterations, "batch_size": plan.batch_size}
    if not any(r.method == SERIES for r in rows):
        model_file = paths["models"] / f"series_{tag}.apmgsrn"
        log(f"series: {dataset}, trained as apmgsrn train does ({len(series)} steps)")
        result = fit_series(series, setup.field, setup.training, model_file, device, resume=True,
                            progress=progress, stepwise=setup.stepwise, packing=setup.packing, plan=setup.record())
        trained = load(model_file)
        measured = [SeriesStepRow(**common, method=SERIES, step=t, file=series.step_name(t), psnr=evaluation.psnr,
                                  psnr_between=between_psnr(trained.step_field(t), series.read(t), t,
                                                            plan.between_points),
                                  max_abs_error=evaluation.max_abs_error, file_bytes=result.model_bytes,
                                  train_seconds=result.seconds, threads=torch.get_num_threads(),
                                  load_average=os.getloadavg()[0], cpu=_cpu(), model_file=str(model_file))
                    for t, evaluation in enumerate(result.evaluation.steps)]
        for row in measured:  # all at once, once every step is measured: a rerun finds all or none
            append_row(paths["csv"], row)
        rows += measured
        psnrs = [row.psnr for row in measured]
        log(f"series: {result.model_bytes:,} bytes, {result.seconds:.1f} s, steps {min(psnrs):.2f} .. "
            f"{max(psnrs):.2f} dB")
    done = {r.step for r in rows if r.method == OWN}
    field_config, train_config = volume_configs(TrainOptions(preset=plan.preset, model=model, iterations=plan.iterations,
                                                             batch_size=plan.batch_size, device=str(device), seed=seed))
    for number, t in enumerate(steps, 1):
        if t in done:
            continue
        model_file = paths["models"] / f"step{t:04d}_{tag}.apmgsrn"
        with series.volume(t) as volume:
            result = fit_volume(volume, field_config, train_config, model_file, device, resume=True, progress=False)
        row = SeriesStepRow(**common, method=OWN, step=t, file=series.step_name(t), psnr=result.psnr,
                            psnr_between=between_psnr(load(model_file).field, series.read(t), t,
                                                      plan.between_points),
                            max_abs_error=result.evaluation.max_abs_error, file_bytes=result.model_bytes,
                            train_seconds=result.seconds, threads=torch.get_num_threads(),
                            load_average=os.getloadavg()[0], cpu=_cpu(), model_file=str(model_file))
        append_row(paths["csv"], row)
        rows.append(row)
        done.add(t)
        log(f"[{number}/{len(steps)}] own model of step {t}: {row.psnr:.2f} dB, {row.file_bytes:,} bytes, "
            f"{row.train_seconds:.1f} s")
    return [r for r in rows if r.method == SERIES or r.step in steps]


@dataclass(frozen=True)
class SeriesCriteria:
    """The series criteria on one series' rows (with several seeds, over the seeds' means).

    Attributes:
        steps: the measured steps (those with an own model and the series' figure of at least one seed).
        seeds: the seeds whose series was trained.
        own, series: each step's PSNR, mean over the seeds with both figures, dB.
        own_between, series_between: the same between the voxels, dB.
        differences: series minus own model PSNR of each (of those means), dB.
        pairs: each step's seeds with both figures, and how many of them have the series at least the own model.
        own_bytes: the largest own model file.
        series_bytes: the largest of the seeds' series files.
        step_seconds: one step's training time: the median of the own models'.
        series_seconds: the series' training time (the median over the seeds).
    """

    steps: list[int]
    seeds: list[int]
    own: list[float]
    series: list[float]
    own_between: list[float]
    series_between: list[float]
    differences: list[float]
    pairs: list[tuple[int, int]]
    own_bytes: int
    series_bytes: int
    step_seconds: float
    series_seconds: float

    @property
    def between(self) -> list[float]:
        """Series minus own model between the voxels, each step, dB."""
        return [s - o for s, o in zip(self.series_between, self.own_between)]

    @property
    def steps_at_least(self) -> int:
        return sum(d >= 0 for d in self.differences)

    @property
    def files(self) -> float:
        return self.series_bytes / self.own_bytes

    @property
    def times(self) -> float:
        return self.series_seconds / self.step_seconds

    def met(self) -> dict[str, bool]:
        """Each criterion: met or not."""
        return {"quality": self.steps_at_least == len(self.steps), "file": self.files <= FILE_BOUND,
                "time": self.times <= TIME_BOUND}


def series_criteria(rows: list[SeriesStepRow]) -> SeriesCriteria:
    """The criteria on the rows of one plan (the series' steps and the own models, of one seed or several).

    Raises:
        ApmgsrnError: no step has both figures.
    """
    series = {(r.seed, r.step): r for r in rows if r.method == SERIES}
    own = {(r.seed, r.step): r for r in rows if r.method == OWN}
    paired = sorted(set(series) & set(own))
    if not paired:
        raise ApmgsrnError("no step has both the series' figure and its own model's; run bench series first")
    steps = sorted({t for _, t in paired})
    by_step = {t: [key for key in paired if key[1] == t] for t in steps}

    def mean(table: dict, t: int, value: str) -> float:
        return statistics.fmean(getattr(table[key], value) for key in by_step[t])

    seeds = sorted({seed for seed, _ in series})
    own_psnr = [mean(own, t, "psnr") for t in steps]
    series_psnr = [mean(series, t, "psnr") for t in steps]
    return SeriesCriteria(
        steps=steps, seeds=seeds, own=own_psnr, series=series_psnr,
        own_between=[mean(own, t, "psnr_between") for t in steps],
        series_between=[mean(series, t, "psnr_between") for t in steps],
        differences=[s - o for s, o in zip(series_psnr, own_psnr)],
        pairs=[(len(by_step[t]), sum(series[key].psnr >= own[key].psnr for key in by_step[t])) for t in steps],
        own_bytes=max(own[key].file_bytes for key in paired),
        series_bytes=max(series[seed, steps[0]].file_bytes for seed in seeds if (seed, steps[0]) in series),
        step_seconds=statistics.median(own[key].train_seconds for key in paired),
        series_seconds=statistics.median(series[seed, steps[0]].train_seconds for seed in seeds
                                         if (seed, steps[0]) in series))


def series_report(rows: list[SeriesStepRow], chart_name: str,
                  between_points: int = SeriesPlan.between_points) -> str:
    """Markdown: what was measured, the criteria, every measured step, and the chart."""
    criteria = series_criteria(rows)
    several = len(criteria.seeds) > 1
    first = next(r for r in rows if r.method == SERIES)
    met = criteria.met()
    verdict = ("All three criteria are met." if all(met.values()) else
               "Not met: " + ", ".join(name for name, ok in met.items() if not ok) + ".")
    d, b = criteria.differences, criteria.between

    def worst(method: str, t: int) -> float:
        return max(r.max_abs_error for r in rows if r.method == method and r.step == t)

    seeds_column = " series >= own model, seed by seed |" if several else ""
    lines = ["| step | file | own model dB | series dB | difference dB | between the voxels: own / series dB | "
             "max abs error: own / series | own model s |" + seeds_column,
             "|---|---|---|---|---|---|---|---|" + ("---|" if several else "")]
    for index, t in enumerate(criteria.steps):
        own = [r for r in rows if r.method == OWN and r.step == t]
        pairs, at_least = criteria.pairs[index]
        lines.append(f"| {t} | {own[0].file} | {criteria.own[index]:.2f} | {criteria.series[index]:.2f} | "
                     f"{d[index]:+.2f} | {criteria.own_between[index]:.2f} / {criteria.series_between[index]:.2f} | "
                     f"{worst(OWN, t):.3g} / {worst(SERIES, t):.3g} | "
                     f"{statistics.median(r.train_seconds for r in own):.1f} |"
                     + (f" {at_least} of {pairs} |" if several else ""))
    loads = sorted({f"{r.load_average:.2f}" for r in rows})
    seeds = (f"seeds {criteria.seeds[0]} .. {criteria.seeds[-1]}; every figure below is the mean over the seeds "
             "(a file, the largest; a time, the median)" if several else f"seed {first.seed}")
    pairs = sum(at_least for _, at_least in criteria.pairs), sum(count for count, _ in criteria.pairs)
    seed_by_seed = f"; seed by seed, {pairs[0]} of {pairs[1]} pairs" if several else ""
    return f"""# One model for the series against one model per step

Written by `apmgsrn bench series`.

- Data: {first.dataset}.
- Every model: the {first.model} {first.preset} preset, {first.iterations:,} iterations x {first.batch_size:,} points,
  {seeds}.
- The series: trained as `apmgsrn train` trains it (stepwise, packed); the own models: each on its step alone,
  after the series, on the same machine.
- Machine: {first.cpu}, {first.threads} thread(s); 1-minute load average {loads[0]} .. {loads[-1]}.

| criterion | target | measured |
|---|---|---|
| PSNR on every measured step | >= the step's own model | {criteria.steps_at_least} of {len(criteria.steps)} steps; series minus own model {min(d):+.2f} .. {max(d):+.2f} dB (mean {statistics.fmean(d):+.2f}){seed_by_seed} |
| model file | <= {FILE_BOUND} own model files ({FILE_BOUND * criteria.own_bytes:,} bytes) | {criteria.series_bytes:,} bytes ({criteria.files:.2f} files) |
| training time | <= {TIME_BOUND} x one step ({TIME_BOUND * criteria.step_seconds:.0f} s; one step: the median own model, {criteria.step_seconds:.1f} s) | {criteria.series_seconds:.1f} s ({criteria.times:.2f} x) |

{verdict} Between the voxels, where a renderer samples (not a criterion; {between_points:,} points drawn
uniformly, against the data's trilinear interpolation), series minus own model: {min(b):+.2f} .. {max(b):+.2f} dB.

![PSNR over time]({chart_name})

{chr(10).join(lines)}
"""


def series_chart(rows: list[SeriesStepRow], path: Path) -> None:
    """PSNR of every step of the series, and of the own models at the measured steps (means over the seeds)."""
    series, own = {}, {}
    for r in rows:
        (series if r.method == SERIES else own).setdefault(r.step, []).append(r.psnr)
    steps = sorted(series)
    seeds = len({r.seed for r in rows if r.method == SERIES})
    mean = f" (mean of {seeds} seeds)" if seeds > 1 else ""
    lines = {f"one model for the series{mean}": [statistics.fmean(series[t]) for t in steps],
             f"one model per step (measured steps){mean}": [statistics.fmean(own[t]) if t in own else math.nan
                                                            for t in steps]}
    first = next(r for r in rows if r.method == SERIES)
    psnr_over_time_chart(steps, lines, path, title=f"{first.model} {first.preset}: PSNR of every step")


def _cpu() -> str:
    return platform.processor() or platform.machine()
