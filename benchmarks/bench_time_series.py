"""One model for a whole simulation run against one small model per step (issue 16).

    python benchmarks/bench_time_series.py baseline --threads 1   # 30 independent small models -> CSV
    python benchmarks/bench_time_series.py series --threads 1     # one time-series model (stepwise) -> CSV
    python benchmarks/bench_time_series.py timing --threads 1     # one step's training right before and after
    python benchmarks/bench_time_series.py speed --model M        # decode/render one step: series vs single file
    python benchmarks/bench_time_series.py report                 # docs/time_series_results.md + chart
    ... --kind hybrid                                              # the same with hybrid models (own CSVs, report)
    python benchmarks/bench_time_series.py moving --out DIR        # a series whose structures move (then --data DIR)

Protocol (REFERENCE.md, CPU): 2,000 iterations x 32,768 points, lr 0.01, seed 0, the small preset, PSNR
over every voxel of each step at native resolution, and between the voxels against the data's trilinear
interpolation (``psnr_between``, :func:`between_psnr`). Rows are appended as they finish, so a killed run
continues where it stopped; each row records the 1-minute load average of the machine when it ended.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from apmgsrn.bench.series import SeriesPlan, between_psnr

ROOT = Path(__file__).resolve().parents[1]
SERIES = ROOT.parent / "shared" / "data" / "viscous_fingers_run01"
RESULTS = ROOT / "benchmarks" / "results"
BASELINE_CSV = RESULTS / "time_series_baseline.csv"
BASELINE_FIELDS = ["step", "file", "psnr", "max_abs_error", "seconds", "iterations", "model_bytes", "parameters",
                   "threads", "load_average", "cpu", "psnr_between"]
#: A kind's series CSV; ``_seedN`` beside it (``series --seed N --csv ...``) and beside the baseline CSV: lines of
#: the chart, and the criterion on the means over seeds, when present (:func:`seed_rows`).
SERIES_CSV = RESULTS / "time_series_model.csv"
SERIES_FIELDS = ["step", "file", "psnr", "max_abs_error", "model_bytes", "train_seconds", "iterations", "config",
                 "threads", "load_average", "cpu", "psnr_between"]
TIMING_CSV = RESULTS / "time_series_timing.csv"
TIMING_FIELDS = ["what", "seconds", "iterations", "threads", "load_average_start", "load_average_end", "cpu"]
SPEED_CSV = RESULTS / "time_series_speed.csv"
SPEED_FIELDS = ["what", "series_seconds", "single_seconds", "repeats", "threads", "load_average", "cpu"]
DOCS = ROOT / "docs"
CHART = DOCS / "images" / "time_series_psnr.png"
#: Model kinds compared: APMGSRN's files keep the names above; another kind's add ``_KIND``.
KINDS = ("apmgsrn", "hybrid")
#: Other series models drawn in a kind's chart for comparison (label -> CSV of the series command), when kept.
COMPARED = {"hybrid": {
    "hybrid small per step, uniform voxel points (the default until 2026-11-25)":
        RESULTS / "time_series_baseline_hybrid_uniform.csv",
    "hybrid series before the fine-tune towards the packing (2026-11-25, 4.73 files)":
        RESULTS / "time_series_model_hybrid_20261125.csv",
    "hybrid series with 50 fine-tune iterations towards the packing (2026-11-27 morning, 4.65 files)":
        RESULTS / "time_series_model_hybrid_20261127.csv",
    "hybrid series with 200 at half the batch (2026-11-27 third session, seed 0, 4.76 files, 5.33x with its packing)":
        RESULTS / "time_series_model_hybrid_20261127b.csv",
    "hybrid series, start model at 2,000 iterations (2026-11-27 eighth session, seed 0, 4.66 files)":
        RESULTS / "time_series_model_hybrid_start2000.csv",
    "hybrid series, steps with half their points between the voxels (2026-11-28 tenth session, seed 0, 4.67 files)":
        RESULTS / "time_series_model_hybrid_between.csv",
    "APMGSRN series (4.6 files)": SERIES_CSV}}


def for_kind(path: Path, kind: str) -> Path:
    """The CSV, report or chart of model kind ``kind``."""
    return path if kind == "apmgsrn" else path.with_name(f"{path.stem}_{kind}{path.suffix}")


def seed_paths(path: Path, kind: str) -> dict[int, Path]:
    """Seed -> a kind's CSV (seed 0) and its ``_seedN`` siblings (``baseline``/``series --seed N --csv ...``), in
    seed order (the siblings where they exist)."""
    first = for_kind(path, kind)
    found = {0: first} | {int(p.stem.rsplit("_seed", 1)[1]): p for p in first.parent.glob(f"{first.stem}_seed*.csv")
                          if p.stem.rsplit("_seed", 1)[1].isdigit()}
    return dict(sorted(found.items()))


def seed_rows(path: Path, kind: str) -> dict[int, dict[int, float]]:
    """Seed -> step -> PSNR of :func:`seed_paths`' CSVs, where they hold rows."""
    rows = {seed: {int(r["step"]): float(r["psnr"]) for r in _done_rows(p)}
            for seed, p in seed_paths(path, kind).items()}
    return {seed: steps for seed, steps in rows.items() if steps}


def seed_mean(seeds: dict[int, dict[int, float]], step: int) -> float:
    """The mean PSNR of ``step`` over the seeds of :func:`seed_rows`; NaN where a seed lacks the step."""
    if not all(step in rows for rows in seeds.values()):
        return math.nan
    return sum(rows[step] for rows in seeds.values()) / len(seeds)


def _train_config(args: argparse.Namespace, **given):
    """The protocol's training config for ``args.kind`` (its own training defaults, then ``given``)."""
    from apmgsrn.models.registry import training_defaults
    from apmgsrn.training.trainer import TrainConfig

    return TrainConfig(**{"iterations": args.iterations, "batch_size": args.batch_size, "lr": 0.01, "seed": 0,
                          **training_defaults(args.kind), **given})


def _cpu() -> str:
    return platform.processor() or platform.machine()


def _done_rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _append(path: Path, fields: list[str], row: dict) -> None:
    """One row onto a CSV (its header first where it is new); a table written before a column was added keeps
    its own columns."""
    new = not path.exists()
    if not new:
        with open(path, newline="") as f:
            fields = next(csv.reader(f), fields)
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        if new:
            writer.writeheader()
        writer.writerow(row)


def run_baseline(args: argparse.Namespace) -> None:
    """One independent small model per step, trained on that step alone under the protocol."""
    import apmgsrn
    from apmgsrn.data import open_volume
    from apmgsrn.models.registry import preset_config
    from apmgsrn.training.fit import fit_volume

    files = list(enumerate(_series_files(args.data)))
    if args.steps:
        files = [files[int(step)] for step in args.steps.split(",")]  # a subset, in the order given
    config = _train_config(args, seed=args.seed,
                           **({} if args.error_sampling is None else {"error_sampling": args.error_sampling}))
    with tempfile.TemporaryDirectory() as tmp:
        for step, path in reversed(files) if args.reverse else files:
            # Read again before every step: a second process may share the table (one from each end).
            if path.name in {row["file"] for row in _done_rows(args.csv)}:
                continue
            volume = open_volume(path)
            result = fit_volume(volume, preset_config(args.kind, "small"), config, Path(tmp) / "m.apmgsrn",
                                torch.device("cpu"), progress=False)
            between = between_psnr(apmgsrn.load(Path(tmp) / "m.apmgsrn").field, volume.to_numpy(), step)
            row = {"step": step, "file": path.name, "psnr": f"{result.psnr:.4f}",
                   "max_abs_error": f"{result.max_abs_error:.6g}", "seconds": f"{result.seconds:.2f}",
                   "iterations": result.iterations, "model_bytes": result.model_bytes,
                   "parameters": result.field.parameter_count(), "threads": torch.get_num_threads(),
                   "load_average": f"{os.getloadavg()[0]:.2f}", "cpu": _cpu(), "psnr_between": f"{between:.4f}"}
            _append(args.csv, BASELINE_FIELDS, row)
            print(" ".join(f"{k}={v}" for k, v in row.items() if k != "cpu"), flush=True)


def _series_files(folder: Path) -> list[Path]:
    """The volume files of a folder (.vti, .npy, .nc, ...), ordered by their step numbers as ``apmgsrn train``
    orders them (``step_2`` before ``step_10``; a gap in the numbering is refused). Any other series ``train``
    reads (a glob, a ``.pvd``, a file with a time dimension) is measured by ``apmgsrn bench series``."""
    from apmgsrn.data.readers import SUPPORTED_SUFFIXES
    from apmgsrn.series.data import order_by_step_number

    suffixes = {s for names in SUPPORTED_SUFFIXES.values() for s in names}
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in suffixes)
    return [path for _, path in order_by_step_number(files)]


def run_series(args: argparse.Namespace) -> None:
    """One time-series model for every step, through ``fit_series`` (the ``train`` command's pipeline)."""
    import apmgsrn
    from apmgsrn.series.data import open_series
    from apmgsrn.models.registry import preset_config
    from apmgsrn.series.field import series_config
    from apmgsrn.series.fit import fit_series
    from apmgsrn.series.packing import SeriesPacking, default_series_packing
    from apmgsrn.recipes import SERIES
    from apmgsrn.series.steps import StepwiseConfig, stepwise_config
    from apmgsrn.series.fit import series_budget

    series = open_series([str(p) for p in _series_files(args.data)])
    small = preset_config(args.kind, "small")
    if args.series_training == "stepwise":
        joint = [name for name in ("basis", "coefficients", "residual", "storage", "series_iterations")
                 if getattr(args, name) is not None]
        if joint:
            raise SystemExit(f"--{joint[0].replace('_', '-')} shapes a joint model: add --series-training joint")
        iterations, config = args.iterations, stepwise_config(small, len(series))
        start = int(args.start) if args.start.isdigit() else args.start
        stepwise = StepwiseConfig(start=start, step_iterations=args.step_iterations)
        packing = (default_series_packing(config, series.shape, iterations) if args.bits is None
                   else SeriesPacking(args.bits, min_bits=args.bits))
        if args.qat_iterations is not None:
            packing = replace(packing, qat_iterations=args.qat_iterations)
        voxel_fraction = SERIES.voxel_fraction if args.voxel_fraction is None else args.voxel_fraction
        anchored = args.anchored_grids
        if anchored is None:  # the hybrid's domain levels cover the domain: nothing to anchor
            anchored = SERIES.anchored_grids if args.kind == "apmgsrn" else 0
    else:
        iterations = args.series_iterations or series_budget(args.iterations, len(series))
        config = series_config(small, len(series), args.basis, args.coefficients, args.residual, args.storage)
        stepwise, packing = None, None
        voxel_fraction, anchored = args.voxel_fraction or 0.0, args.anchored_grids or 0
    train_config = _train_config(args, iterations=iterations, seed=args.seed, voxel_fraction=voxel_fraction,
                                 anchored_grids=anchored)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "series.apmgsrn"
        result = fit_series(series, config, train_config, out, torch.device("cpu"), progress=args.progress,
                            stepwise=stepwise, packing=packing)
        model_bytes = out.stat().st_size
        if args.keep:
            args.keep.write_bytes(out.read_bytes())
        model = apmgsrn.load(out)
        report = model.description.packing.report if packing is not None else {}
        between = [between_psnr(model.step_field(t), series.read(t), t) for t in result.evaluation.indices]
        bits, qat = report.get("bits"), report.get("qat_iterations")  # what ran: a long series shortens the fine-tune
    if stepwise is not None:
        described = (f"{args.kind} stepwise start={args.start} iterations={iterations} bits={bits} "
                     f"voxel_fraction={voxel_fraction:g} anchored_grids={anchored}"
                     + (f" step_sparsity={stepwise.sparsity(args.kind):g}" if stepwise.sparsity(args.kind) else "")
                     + (f" error_sampling={train_config.error_sampling:g}" if train_config.error_sampling else "")
                     + (f" qat_iterations={qat}" if qat else "")
                     + (f" step_iterations={args.step_iterations}" if args.step_iterations else "")
                     + (f" seed={args.seed}" if args.seed else ""))
    else:
        described = f"basis={config.series.basis} {config.series.coefficients} residual={config.series.residual} " \
                    f"storage={config.series.storage} iterations={iterations} voxel_fraction={voxel_fraction:g}" \
                    + (f" anchored_grids={anchored}" if anchored else "")
    if args.csv.exists():
        args.csv.unlink()  # one model: the table is replaced, not appended to
    for step, evaluation, measured in zip(result.evaluation.indices, result.evaluation.steps, between):
        _append(args.csv, SERIES_FIELDS, {
            "step": step, "file": series.step_name(step), "psnr": f"{evaluation.psnr:.4f}",
            "max_abs_error": f"{evaluation.max_abs_error:.6g}", "model_bytes": model_bytes,
            "train_seconds": f"{result.seconds:.2f}", "iterations": result.iterations, "config": described,
            "threads": torch.get_num_threads(), "load_average": f"{(load + os.getloadavg()[0]) / 2:.2f}",
            "cpu": _cpu(), "psnr_between": f"{measured:.4f}"})
    print(f"series model: {model_bytes:,} bytes, {result.seconds:.1f} s, lowest step PSNR "
          f"{min(e.psnr for e in result.evaluation.steps):.2f} dB", flush=True)
    _report_kernels()


def _report_kernels() -> None:
    """Which fused CPU kernels this run used: one that could not be built falls back to the reference silently,
    which changes the timings (and the numbers, by float32 rounding)."""
    from apmgsrn.ops import field_cpu, field_train_cpu

    for name, library in (("fused inference", field_cpu.LEVEL_LIBRARY), ("fused training", field_train_cpu.LIBRARY)):
        state = ("not used" if not library.tried else "used" if library.error is None
                 else f"FAILED, the reference ran: {library.error}")
        print(f"{name} kernel: {state}", flush=True)


def write_moving(args: argparse.Namespace) -> None:
    """A series whose structures move: one real volume (or the first steps of a real series, ``--series``)
    shifted along an axis by ``--shift`` voxels more at every step (periodic wrap), written as ``step_NN.npy``
    files to ``--out``. The steps share everything but where things are (or, from a series, change as the run
    does and travel too), which is what a placement shared by all steps finds hardest."""
    import numpy as np

    from apmgsrn.data import open_volume

    if args.series is not None:
        files = _series_files(args.series)[: args.steps]
        if len(files) < args.steps:
            raise SystemExit(f"{args.series} holds {len(files)} steps, fewer than --steps {args.steps}")
        volumes = [open_volume(f).to_numpy() for f in files]  # [D, H, W] each
    else:
        volumes = [open_volume(args.volume).to_numpy()] * args.steps
    axis = {"x": 2, "y": 1, "z": 0}[args.axis]
    args.out.mkdir(parents=True, exist_ok=True)
    for step, values in enumerate(volumes):
        np.save(args.out / f"step_{step:02d}.npy", np.roll(values, step * args.shift, axis=axis))
    print(f"wrote {args.steps} steps of {volumes[0].shape} to {args.out}, shifted {args.shift} voxels per step "
          f"along {args.axis}")


def write_upsampled(args: argparse.Namespace) -> None:
    """Every step of a series folder (``--series``) resampled to ``--size``^3 (trilinear, corner-aligned), written
    as ``step_NNN.npy`` files to ``--out``: the same run at a resolution where the error guide measures one voxel
    per block and every step holds more voxels than the batches see."""
    import numpy as np

    from apmgsrn.data import open_volume

    args.out.mkdir(parents=True, exist_ok=True)
    files = _series_files(args.series)
    for step, path in enumerate(files):
        values = torch.from_numpy(np.ascontiguousarray(open_volume(path).to_numpy(), dtype=np.float32))
        resized = torch.nn.functional.interpolate(values[None, None], size=(args.size,) * 3, mode="trilinear",
                                                  align_corners=True)[0, 0]
        np.save(args.out / f"step_{step:03d}.npy", resized.numpy())
    print(f"wrote {len(files)} steps of {args.size}^3 to {args.out}")


def write_midpoints(args: argparse.Namespace) -> None:
    """Every step of a series folder (``--series``) and, between each two, their mean, written as ``step_NNN.npy``
    files to ``--out`` (30 steps give 59): the same run as if written out twice as often, each step changing
    about half as much from the one before (the mean is a linear stand-in for the state in between)."""
    import numpy as np

    from apmgsrn.data import open_volume

    args.out.mkdir(parents=True, exist_ok=True)
    files = _series_files(args.series)
    previous, written = None, 0
    for path in files:
        values = np.ascontiguousarray(open_volume(path).to_numpy(), dtype=np.float32)
        if previous is not None:
            np.save(args.out / f"step_{written:03d}.npy", ((previous + values) / 2).astype(np.float32))
            written += 1
        np.save(args.out / f"step_{written:03d}.npy", values)
        previous, written = values, written + 1
    print(f"wrote {written} steps of {previous.shape} to {args.out}: {len(files)} steps and the means between them")


def run_timing(args: argparse.Namespace) -> None:
    """Train one step's small model under the protocol and record how long it took (for the 5x comparison,
    measured right before and right after the series model, on the same machine and threads)."""
    from apmgsrn.data import open_volume
    from apmgsrn.models.registry import preset_config
    from apmgsrn.training.fit import fit_volume

    path = _series_files(args.data)[args.step]
    config = _train_config(args)
    start_load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        result = fit_volume(open_volume(path), preset_config(args.kind, "small"), config, Path(tmp) / "m.apmgsrn",
                            torch.device("cpu"), progress=False)
    _append(args.csv, TIMING_FIELDS, {"what": f"one step ({path.name}) {args.label}", "seconds": f"{result.seconds:.2f}",
                                      "iterations": result.iterations, "threads": torch.get_num_threads(),
                                      "load_average_start": f"{start_load:.2f}",
                                      "load_average_end": f"{os.getloadavg()[0]:.2f}", "cpu": _cpu()})
    print(f"one step: {result.seconds:.1f} s", flush=True)


def run_speed(args: argparse.Namespace) -> None:
    """Decode and render one step from the series file, against the same step saved as a single-step model file.

    The single-step file holds exactly the step's materialised network, so both evaluate the same values with
    the same network shape. Timed apart: opening the file (a packed series decodes every step's grids once),
    then decoding and rendering the step with the model open (the series materialises the step's features),
    and opening plus decoding together, as a one-off command does. Each row keeps the fastest of ``repeats``
    interleaved runs, after one warm-up, so a burst of load hits both alike.
    """
    import apmgsrn
    from apmgsrn.io import SourceInfo, save_field
    from apmgsrn.rendering import Camera, RendererConfig, VolumeRenderer, make_transfer_function

    series_model = apmgsrn.load(args.model)
    step = args.step
    tf = make_transfer_function("Cool to Warm", series_model.description.series.steps[step].value_range)
    camera = Camera.orbit(width=args.image_size, height=args.image_size)
    config = RendererConfig(samples_per_ray=256)

    def timed(action) -> float:
        start = time.perf_counter()
        action()
        return time.perf_counter() - start

    with tempfile.TemporaryDirectory() as tmp:
        single = Path(tmp) / "step.apmgsrn"
        save_field(single, series_model.step_field(step), SourceInfo(), {})
        models = {"series": (args.model, step), "single": (single, None)}
        opened = {name: apmgsrn.load(path) for name, (path, _) in models.items()}
        actions = {
            "open the model file": lambda name: apmgsrn.load(models[name][0]),
            "decode one step (64^3), model open": lambda name: opened[name].decode(time=models[name][1]),
            f"render one step ({args.image_size}^2, 256 spp), model open": lambda name: VolumeRenderer(
                opened[name].step_field(models[name][1]), tf, config).render(camera),
            "open the file and decode one step": lambda name: apmgsrn.load(models[name][0]).decode(
                time=models[name][1]),
        }
        load = os.getloadavg()[0]
        for what, action in actions.items():
            times = {name: [] for name in models}
            for name in models:
                action(name)  # warm-up: kernels, caches
            for _ in range(args.repeats):
                for name in models:
                    times[name].append(timed(lambda: action(name)))
            _append(args.csv, SPEED_FIELDS, {
                "what": f"{what}, step {step}", "series_seconds": f"{min(times['series']):.4f}",
                "single_seconds": f"{min(times['single']):.4f}", "repeats": args.repeats,
                "threads": torch.get_num_threads(), "load_average": f"{(load + os.getloadavg()[0]) / 2:.2f}",
                "cpu": _cpu()})
            print(f"{what}: series {min(times['series']):.3f} s, single {min(times['single']):.3f} s", flush=True)


def _between_section(kind: str) -> str:
    """Each seed's steps over the voxels and between them (:func:`between_psnr`), own models against the series,
    where the baseline and series CSVs of a seed (:func:`seed_paths`) both measured between the voxels."""
    own_paths, series_paths = seed_paths(BASELINE_CSV, kind), seed_paths(SERIES_CSV, kind)
    own_path, series_path = own_paths[0], series_paths[0]
    found = {}
    for seed in sorted(set(own_paths) & set(series_paths)):
        rows = [{int(r["step"]): r for r in _done_rows(p) if r.get("psnr_between")}
                for p in (own_paths[seed], series_paths[seed])]
        steps = sorted(set(rows[0]) & set(rows[1]))
        if steps:
            found[seed] = (rows, steps)
    if not found:
        return ""
    lines = ["| seed | step | own model: voxels / between dB | series: voxels / between dB | "
             "series minus own: voxels / between dB |", "|---|---|---|---|---|"]
    gaps = []
    for seed, ((own, series), steps) in found.items():
        for t in steps:
            o = float(own[t]["psnr"]), float(own[t]["psnr_between"])
            m = float(series[t]["psnr"]), float(series[t]["psnr_between"])
            gaps.append((m[0] - o[0], m[1] - o[1]))
            lines.append(f"| {seed} | {t} | {o[0]:.2f} / {o[1]:.2f} | {m[0]:.2f} / {m[1]:.2f} | "
                         f"{m[0] - o[0]:+.2f} / {m[1] - o[1]:+.2f} |")
    return f"""
**Between the voxels too.** A renderer samples between the voxels, where a model is trained on the data's
trilinear interpolation; there each model is measured at {SeriesPlan.between_points:,} points drawn uniformly in the domain
(the same for both models of a step) against that interpolation, over the step's value range
(the `psnr_between` column of `{own_path.name}`, `{series_path.name}` and their `_seedN` siblings). Series minus own
model: {min(g[0] for g in gaps):+.2f} .. {max(g[0] for g in gaps):+.2f} dB over the voxels,
{min(g[1] for g in gaps):+.2f} .. {max(g[1] for g in gaps):+.2f} dB between them.

{chr(10).join(lines)}
"""


def _seeds_section(own: dict[int, dict[int, float]], series: dict[int, dict[int, float]]) -> str:
    """The criterion on the means over seeds, and the per-step means, when more than one seed of both sides was
    run (on the steps every seed of both has)."""
    if len(own) < 2 or len(series) < 2:
        return ""
    steps = sorted(set.intersection(*(set(p) for p in [*own.values(), *series.values()])))
    if not steps:
        return ""
    mean = {name: {t: seed_mean(rows, t) for t in steps} for name, rows in (("own", own), ("series", series))}
    differences = [mean["series"][t] - mean["own"][t] for t in steps]
    above = sum(d >= 0 for d in differences)
    table = "\n".join(f"| {t} | {mean['own'][t]:.2f} | {mean['series'][t]:.2f} | {differences[i]:+.2f} |"
                       for i, t in enumerate(steps))
    return (f"| PSNR on every step, means of seeds {', '.join(map(str, own))} (own) and "
            f"{', '.join(map(str, series))} (series) | >= the step's own small models | {above} of {len(steps)} "
            f"steps; difference {min(differences):+.2f} .. {max(differences):+.2f} dB |\n\n"
            "Means over the seeds (one seed's models of the same step differ by up to a dB or more):\n\n"
            "| step | own small models, mean | series, mean | difference dB |\n|---|---|---|---|\n"
            f"{table}\n")


def write_report(out: Path, timing_steps: list[int] | None = None, kind: str = "apmgsrn") -> None:
    """The per-step table (both methods side by side), the criteria, and the chart.

    Args:
        out: the Markdown file.
        timing_steps: baseline steps whose training time is the one-step time of the 5x criterion (those
            trained while the series model trained, under the same load); None: the timing table, else the
            median baseline row.
        kind: the model kind whose CSVs are read (the chart is written for it too).
    """
    from apmgsrn.atomic import atomic_write_text
    from apmgsrn.bench.charts import psnr_over_time_chart

    baseline = {int(r["step"]): r for r in _done_rows(for_kind(BASELINE_CSV, kind))}
    series = {int(r["step"]): r for r in _done_rows(for_kind(SERIES_CSV, kind))}
    chart = for_kind(CHART, kind)
    steps = sorted(set(baseline) & set(series))
    if not steps:
        raise SystemExit("run the baseline and series commands first")
    lines = ["| step | file | one model per step: PSNR dB | one model for the series: PSNR dB | difference dB | "
             "max abs error (per step / series) |", "|---|---|---|---|---|---|"]
    for t in steps:
        b, m = baseline[t], series[t]
        lines.append(f"| {t} | {b['file']} | {float(b['psnr']):.2f} | {float(m['psnr']):.2f} | "
                     f"{float(m['psnr']) - float(b['psnr']):+.2f} | {float(b['max_abs_error']):.3g} / "
                     f"{float(m['max_abs_error']):.3g} |")
    differences = [float(series[t]["psnr"]) - float(baseline[t]["psnr"]) for t in steps]
    at_least = sum(d >= 0 for d in differences)
    single_bytes = max(int(baseline[t]["model_bytes"]) for t in steps)
    series_bytes = int(series[steps[0]]["model_bytes"])
    series_seconds = float(series[steps[0]]["train_seconds"])
    timing = _done_rows(for_kind(TIMING_CSV, kind))
    if timing_steps:
        measured_steps = [t for t in timing_steps if t in baseline]
        step_seconds = sum(float(baseline[t]["seconds"]) for t in measured_steps) / len(measured_steps)
        measured = ", ".join(f"step {t}: {float(baseline[t]['seconds']):.0f} s" for t in measured_steps)
        step_source = (f"the mean of the single-step trainings that ran at the same time as the series model "
                       f"on the same machine ({measured})")
    elif timing:
        step_seconds = sum(float(r["seconds"]) for r in timing) / len(timing)
        measured = ", ".join(f"{float(r['seconds']):.1f} s" for r in timing)
        labels = "; ".join(sorted({r["what"].split(") ", 1)[-1] for r in timing if ") " in r["what"]}))
        step_source = (f"the mean of {len(timing)} single-step trainings of the timing table ({measured}"
                       + (f"; {labels}" if labels else "") + ")")
    else:
        step_seconds = sorted(float(baseline[t]["seconds"]) for t in steps)[len(steps) // 2]
        step_source = "the median single-step training of the baseline table"
    speed = _done_rows(for_kind(SPEED_CSV, kind))
    speed_lines = "\n".join(
        f"| {r['what']} | {float(r['series_seconds']):.3f} s | {float(r['single_seconds']):.3f} s | "
        f"{float(r['series_seconds']) / float(r['single_seconds']):.2f} |" for r in speed)
    config = series[steps[0]]["config"]
    baseline_note = "" if len(steps) == 30 else (
        f" Independent models were trained for {len(steps)} of the 30 steps ({', '.join(map(str, steps))}): "
        "the others were not trained for lack of machine time (each took "
        f"{min(float(baseline[t]['seconds']) for t in steps):.0f} to "
        f"{max(float(baseline[t]['seconds']) for t in steps):.0f} s on this shared machine).")
    loads = ", ".join(sorted({r["load_average"] for r in series.values()}))
    seeds_text = _seeds_section(seed_rows(BASELINE_CSV, kind), seed_rows(SERIES_CSV, kind)) + _between_section(kind)
    text = f"""# One model for a whole run: measured (issue 16)

Written by `python benchmarks/bench_time_series.py report` from `benchmarks/results/time_series_*.csv`.
Data: the 30 consecutive steps of `viscous_fingers_run01` (64^3, float32). Protocol: 2,000 iterations x 32,768
points per independent small model (lr 0.01, seed 0); the series model `{config}`, same batch, lr and seed.
CPU: {series[steps[0]]['cpu']}, {series[steps[0]]['threads']} thread(s); the machine was shared with other work
(1-minute load average during the series run: {loads}; per baseline row in its CSV).{baseline_note}

| criterion | target | measured |
|---|---|---|
| PSNR on every step | >= the step's own small model | {at_least} of {len(steps)} steps; difference {min(differences):+.2f} .. {max(differences):+.2f} dB (mean {sum(differences) / len(differences):+.2f}) |
| model file | <= 5 small models ({5 * single_bytes:,} bytes) | {series_bytes:,} bytes ({series_bytes / single_bytes:.2f} small models) |
| training time | <= 5 x one step ({5 * step_seconds:.0f} s) | {series_seconds:.0f} s ({series_seconds / step_seconds:.2f} x {step_source}) |
{seeds_text}
Decoding or rendering one step, the series file against the same step saved as a single-step model file
(identical network shape and values). With the model open a step costs what a single-step model costs (the
series materialises the step's features); opening the series file is a one-off cost for all its steps (a
packed series decodes every step's grids once). Fastest of several interleaved runs after a warm-up:

| what | series file | single-step file | ratio |
|---|---|---|---|
{speed_lines}

![PSNR over time](images/{chart.name})

{chr(10).join(lines)}
"""
    atomic_write_text(out, text, "report")
    every = sorted(series)
    lines = {}
    for name, path in (("one small model per step", BASELINE_CSV), ("one model for the series", SERIES_CSV)):
        seeds = seed_rows(path, kind)  # seed -> step -> PSNR; their mean where a step has every seed
        label = name if len(seeds) == 1 else f"{name}, mean of seeds {', '.join(map(str, seeds))}"
        lines[label] = [seed_mean(seeds, t) for t in every]
    for label, path in COMPARED.get(kind, {}).items():
        other = {int(r["step"]): float(r["psnr"]) for r in _done_rows(path)}
        if other:
            lines[label] = [other.get(t, math.nan) for t in every]
    psnr_over_time_chart(every, lines, chart, title=f"viscous fingering, 30 steps: PSNR of every step ({kind})")
    print(f"wrote {out} and {chart}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    base = sub.add_parser("baseline", help="one small model per step")
    base.add_argument("--csv", type=Path)
    base.add_argument("--reverse", action="store_true", help="last step first (a second process shares the work)")
    base.add_argument("--steps", help="only these steps, e.g. 10,15,20,25 (default: all)")
    base.add_argument("--seed", type=int, default=0, help="the models' seed (the protocol's is 0)")
    base.add_argument("--error-sampling", type=float,
                      help="share of the voxel points drawn where the model is wrong (default: the kind's own)")
    series = sub.add_parser("series", help="one model for the whole series")
    series.add_argument("--csv", type=Path)
    series.add_argument("--basis", type=int)
    series.add_argument("--coefficients")
    series.add_argument("--residual", type=int)
    series.add_argument("--storage")
    series.add_argument("--series-iterations", type=int, help="default: the train command's series budget")
    series.add_argument("--keep", type=Path, help="also keep the model file here")
    series.add_argument("--progress", action="store_true")
    series.add_argument("--series-training", choices=("stepwise", "joint"), default="stepwise")
    series.add_argument("--start", default="auto", help="stepwise: the start step (auto, first, last)")
    series.add_argument("--bits", type=int,
                        help="stepwise: bit width the grids are packed to (default: as train packs, 10 bits within "
                             "five single-step models)")
    series.add_argument("--step-iterations", type=int,
                        help="stepwise: a step's base fine-tune iterations (default: a tenth of --iterations)")
    series.add_argument("--qat-iterations", type=int,
                        help="stepwise: every step's quantisation-aware fine-tune before packing (train's option; "
                             "default: train's)")
    series.add_argument("--seed", type=int, default=0)
    series.add_argument("--voxel-fraction", type=float,
                        help="share of every batch on voxels (default: stepwise 0.5, joint 0)")
    series.add_argument("--anchored-grids", type=int,
                        help="grids that keep their starting placement (default: stepwise 1, joint 0)")
    timing = sub.add_parser("timing", help="one step's training time, for the 5x comparison")
    timing.add_argument("--csv", type=Path)
    timing.add_argument("--step", type=int, default=15)
    timing.add_argument("--label", default="")
    speed = sub.add_parser("speed", help="decode/render one step: the series file against a single-step file")
    speed.add_argument("--csv", type=Path, default=SPEED_CSV)
    speed.add_argument("--model", type=Path, required=True, help="a series model file (series --keep)")
    speed.add_argument("--step", type=int, default=15)
    speed.add_argument("--repeats", type=int, default=5)
    speed.add_argument("--image-size", type=int, default=256)
    speed.add_argument("--threads", type=int, default=1)
    moving = sub.add_parser("moving", help="write a series of one volume shifted further at every step")
    moving.add_argument("--volume", type=Path, default=ROOT.parent / "shared" / "data" / "viscous_fingers_t050.vti")
    moving.add_argument("--steps", type=int, default=10)
    moving.add_argument("--series", type=Path, help="shift the first --steps steps of this series folder instead")
    moving.add_argument("--shift", type=int, default=4, help="voxels per step")
    moving.add_argument("--axis", choices=("x", "y", "z"), default="x")
    moving.add_argument("--out", type=Path, required=True)
    upsample = sub.add_parser("upsample", help="write every step of a series resampled to a larger grid")
    upsample.add_argument("--series", type=Path, default=SERIES)
    upsample.add_argument("--size", type=int, default=128)
    upsample.add_argument("--out", type=Path, required=True)
    midpoints = sub.add_parser("midpoints", help="write every step of a series and the mean between each two")
    midpoints.add_argument("--series", type=Path, default=SERIES)
    midpoints.add_argument("--out", type=Path, required=True)
    report = sub.add_parser("report", help="the per-step table and chart in docs/")
    report.add_argument("--out", type=Path)
    for p in (base, series, timing):
        p.add_argument("--data", type=Path, default=SERIES, help="a folder of volume files, one per step")
        p.add_argument("--iterations", type=int, default=2000)
        p.add_argument("--batch-size", type=int, default=32768)
    for p in (base, series, timing, moving, upsample, midpoints, report):
        p.add_argument("--threads", type=int, default=1)
    for p in (base, series, timing, report):
        p.add_argument("--kind", choices=KINDS, default="apmgsrn", help="the model kind (default apmgsrn)")
    report.add_argument("--timing-steps", help="baseline steps trained alongside the series model, e.g. 15,10,20,25: "
                                               "their mean time is the one-step time of the 5x criterion")
    args = parser.parse_args()
    defaults = {"baseline": BASELINE_CSV, "series": SERIES_CSV, "timing": TIMING_CSV}
    if args.command in defaults and args.csv is None:
        args.csv = for_kind(defaults[args.command], args.kind)
    if args.command == "report" and args.out is None:
        args.out = for_kind(DOCS / "time_series_results.md", args.kind)
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    if args.command == "baseline":
        run_baseline(args)
    elif args.command == "series":
        run_series(args)
    elif args.command == "timing":
        run_timing(args)
    elif args.command == "speed":
        run_speed(args)
    elif args.command == "moving":
        write_moving(args)
    elif args.command == "upsample":
        write_upsampled(args)
    elif args.command == "midpoints":
        write_midpoints(args)
    else:
        write_report(args.out, [int(t) for t in args.timing_steps.split(",")] if args.timing_steps else None,
                     args.kind)
    print(f"done in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
