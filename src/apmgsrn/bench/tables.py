"""Markdown tables of benchmark results (the layout of the paper's Table 1)."""

from __future__ import annotations

import math

from apmgsrn.bench.results import (
    MODEL_TITLES,
    SIZE_ORDER,
    CompressRow,
    QualityRow,
    Summary,
    group_quality,
    ordered,
)
from apmgsrn.choices import COMPRESSORS, MODEL_KINDS


def quality_tables(rows: list[QualityRow]) -> str:
    """PSNR, real size and training time tables, one row per volume, ``S / M / L`` per model.

    The best mean PSNR of each volume and size is in bold. With several seeds a cell reads
    ``mean ± standard deviation``; an empty cell (``–``) was not run.

    Args:
        rows: results of ``bench quality`` (any subset of combinations).

    Returns:
        Markdown text: PSNR table, largest-error table, size table, compression table, training-time table and
        the protocol.
    """
    groups = group_quality(rows)
    datasets = list(dict.fromkeys(row.dataset for row in rows))
    models = ordered((row.model for row in rows), MODEL_KINDS)
    sizes = ordered((row.size for row in rows), SIZE_ORDER)
    shapes = {row.dataset: row.shape for row in rows}
    psnr = {key: Summary.of([r.psnr for r in group]) for key, group in groups.items()}
    letters = " / ".join(size[0].upper() for size in sizes)

    lines = ["PSNR (dB) over every voxel; best per volume and size in **bold**.", ""]
    lines.append("| volume | " + " | ".join(f"{MODEL_TITLES.get(m, m)} {letters}" for m in models) + " |")
    lines.append("|---|" + "---|" * len(models))
    for dataset in datasets:
        best = {}
        for size in sizes:
            means = [psnr[(dataset, m, size)].mean for m in models if (dataset, m, size) in psnr]
            means = [v for v in means if math.isfinite(v)]
            best[size] = max(means) if means else None
        cells = []
        for model in models:
            parts = []
            for size in sizes:
                summary = psnr.get((dataset, model, size))
                if summary is None:
                    parts.append("–")
                    continue
                text = _with_spread(summary, 2)
                parts.append(f"**{text}**" if best[size] is not None and summary.mean == best[size] else text)
            cells.append(" / ".join(parts))
        lines.append(f"| {dataset} {shapes[dataset]} | " + " | ".join(cells) + " |")

    def error_cell(group: list[QualityRow]) -> str:
        mean = Summary.of([r.max_abs_error for r in group]).mean
        return f"{mean:.4g}" if math.isfinite(mean) else "–"

    lines += ["", "Largest absolute error over every voxel (data units; mean over seeds, – where not recorded).", ""]
    lines += _per_volume(groups, datasets, models, sizes, error_cell, {d: d for d in datasets})

    lines += ["", "Real model sizes (parameters; their stored bytes, float16 tables of the hybrid included; model "
              "file bytes with metadata).", ""]
    lines.append("| model | size | parameters | stored | file |")
    lines.append("|---|---|---|---|---|")
    for model in models:
        for size in sizes:
            sample = next((r for r in rows if r.model == model and r.size == size), None)
            if sample is None:
                continue
            lines.append(
                f"| {MODEL_TITLES.get(model, model)} | {size} | {sample.parameters:,} | "
                f"{_kilobytes(sample.parameter_bytes)} | {_kilobytes(sample.file_bytes)} |"
            )

    lines += ["", f"Compression ratio, {letters}: the volume's stored bytes (its own dtype) / model file bytes; "
              "in parentheses against float32 where the two differ.", ""]
    dtypes = {row.dataset: row.data_dtype for row in rows}
    lines += _per_volume(groups, datasets, models, sizes,
                         lambda group: _ratio_text(group[0].compression_ratio, group[0].compression_ratio_float32),
                         {d: f"{d} ({dtypes[d]})" for d in datasets})

    lines += ["", f"Training time (s), {letters}.", ""]
    lines += _per_volume(groups, datasets, models, sizes,
                         lambda group: f"{Summary.of([r.train_seconds for r in group]).mean:.0f}",
                         {d: d for d in datasets})

    lines += ["", _protocol(rows), ""]
    return "\n".join(lines)


def _per_volume(groups: dict, datasets: list[str], models: list[str], sizes: list[str], cell, labels: dict) -> list[str]:
    """A table of one row per volume, ``S / M / L`` per model: ``cell(rows of the combination)``, ``–`` for a
    combination not run."""
    letters = " / ".join(size[0].upper() for size in sizes)
    lines = ["| volume | " + " | ".join(f"{MODEL_TITLES.get(m, m)} {letters}" for m in models) + " |",
             "|---|" + "---|" * len(models)]
    for dataset in datasets:
        cells = []
        for model in models:
            parts = [("–" if (dataset, model, size) not in groups else cell(groups[(dataset, model, size)]))
                     for size in sizes]
            cells.append(" / ".join(parts))
        lines.append(f"| {labels[dataset]} | " + " | ".join(cells) + " |")
    return lines


def compress_table(rows: list[CompressRow]) -> str:
    """One line per compressor setting or network: ratio, PSNR, times and query throughput.

    Args:
        rows: results of ``bench compress``.

    Returns:
        Markdown text.
    """
    lines = [
        "| volume | method | setting | ratio | PSNR dB | max error | compress s | decompress s | "
        "decompress Mvox/s | query s | query Mpts/s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.dataset} | {MODEL_TITLES.get(r.method, r.method.upper())} | {r.setting} | "
            f"{_ratio_text(r.compression_ratio, r.compression_ratio_float32)} | {r.psnr:.2f} | "
            f"{r.max_abs_error:.3g} | {r.compress_seconds:.2f} | "
            f"{r.decompress_seconds:.2f} | {r.decompress_voxels_per_second / 1e6:.1f} | {r.query_seconds:.3f} | "
            f"{r.query_points_per_second / 1e6:.2f} |"
        )
    if rows:
        lines += [
            "",
            "Ratio: the volume's stored bytes (its own dtype) / compressed bytes; in parentheses against float32 "
            "(the values every method compressed) where the two differ.",
            f"Query: {rows[0].query_points:,} uniformly random points; a compressor must decompress the "
            "whole volume first and then interpolate, a network evaluates the points directly.",
        ]
    crossover = crossover_lines(rows)
    if crossover:
        lines += ["", *crossover]
    return "\n".join(lines) + "\n"


#: The compressors the networks are compared with, each with the methods (modes) it is measured in: at a
#: ratio, the compressor's best mode there (:func:`compressor_curve`).
COMPRESSOR_FAMILIES = {"SZ3": ("sz3",), "ZFP": ("zfp", "zfp-precision"), "SPERR": ("sperr", "sperr-pwe"),
                       "TTHRESH": ("tthresh",)}


def compressor_psnr_at(curve: list[tuple[float, float]], ratio: float) -> tuple[float, str] | None:
    """A compressor's PSNR at ``ratio`` from its measured ``(ratio, PSNR)`` points.

    Inside the measured ratios: linear in log(ratio) between the two neighbours (``"interpolated"``).
    Above the largest: the PSNR of that largest-ratio point, an upper bound of what the compressor gives at
    ``ratio`` if its quality falls as its ratio grows (``"at most"``). Below the smallest: None.
    """
    curve = sorted(curve)
    if not curve or ratio < curve[0][0]:
        return None
    if ratio >= curve[-1][0]:
        return curve[-1][1], "at most" if ratio > curve[-1][0] else "measured"
    for (r0, p0), (r1, p1) in zip(curve, curve[1:]):
        if r0 <= ratio <= r1:
            if not (math.isfinite(p0) and math.isfinite(p1)):
                return max(p0, p1), "interpolated"
            if r1 == r0:
                return max(p0, p1), "measured"
            share = math.log(ratio / r0) / math.log(r1 / r0)
            return p0 + share * (p1 - p0), "interpolated"
    return None  # unreachable: the ratio lies in the curve's range


def compressor_curve(rows: list[CompressRow], methods: tuple[str, ...]) -> list[tuple[float, float]]:
    """``(ratio, PSNR)`` of ``methods``' rows that no other of them beats at an equal or higher ratio: the
    best the compressor does in any of its modes, by increasing ratio."""
    points = [(r.compression_ratio, r.psnr) for r in rows if r.method in methods]
    return sorted((ratio, psnr) for ratio, psnr in points
                  if not any(p > psnr and q >= ratio for q, p in points if (q, p) != (ratio, psnr)))


def network_frontier(rows: list[CompressRow], same_ratio: float = 0.01) -> list[CompressRow]:
    """The networks no other network beats at an equal or higher ratio (the best choice at each ratio),
    by increasing ratio; ratios within ``same_ratio`` (relative) of each other count as equal."""
    nets = [r for r in rows if r.method not in COMPRESSORS]  # every method but a compressor is a network
    frontier = [
        row for row in nets
        if not any(other.psnr > row.psnr and other.compression_ratio >= row.compression_ratio * (1 - same_ratio)
                   for other in nets)
    ]
    return sorted(frontier, key=lambda r: r.compression_ratio)


def crossover_lines(rows: list[CompressRow]) -> list[str]:
    """Each network of the frontier against each compressor at the same ratio, and the crossover: the
    lowest ratio from which every frontier network compared is ahead. Above a compressor's largest
    measured ratio only a network above that point's PSNR is decided (ahead); the others are not compared.
    Empty without networks or compressors."""
    lines: list[str] = []
    for dataset in dict.fromkeys(r.dataset for r in rows):
        here = [r for r in rows if r.dataset == dataset]
        frontier = network_frontier(here)
        for name, methods in COMPRESSOR_FAMILIES.items():
            curve = compressor_curve(here, methods)
            if not curve or not frontier:
                continue
            if not lines:
                lines += [
                    "Networks against each compressor at the same ratio (the networks no other network beats "
                    "at an equal or higher ratio; the compressor's PSNR interpolated in log(ratio) between its "
                    "measured settings, in whichever of its modes is best there, or, above its largest ratio, "
                    "that point's PSNR: an upper bound).",
                    "",
                    "| volume | network | ratio | network PSNR dB | compressor | compressor PSNR dB | margin dB |",
                    "|---|---|---|---|---|---|---|",
                ]
            verdicts = []
            reach = max(ratio for ratio, _ in curve)
            for row in frontier:
                reference = compressor_psnr_at(curve, row.compression_ratio)
                if reference is None:
                    continue
                value, how = reference
                title = f"{MODEL_TITLES.get(row.method, row.method.upper())} {row.setting}"
                margin = row.psnr - value
                if how == "at most" and not margin > 0:  # below an upper bound: undecided
                    lines.append(f"| {dataset} | {title} | {row.compression_ratio:,.0f} | {row.psnr:.2f} | {name} | "
                                 f"not reached (at most {reach:,.0f}:1 measured) | |")
                    continue
                verdicts.append((row.compression_ratio, margin > 0))
                lines.append(f"| {dataset} | {title} | {row.compression_ratio:,.0f} | {row.psnr:.2f} | {name} | "
                             f"{'≤ ' if how == 'at most' else ''}{value:.2f} | {margin:+.2f} |")
            crossover = None
            for ratio, ahead in reversed(verdicts):
                if not ahead:
                    break
                crossover = ratio
            if not verdicts:
                summary = f"not compared: {name} reached at most {reach:,.0f}:1 with the settings measured"
            else:
                if crossover is None:
                    summary = f"{name} ahead at the highest ratio compared"
                elif crossover == verdicts[0][0]:
                    summary = f"networks ahead of {name} at every ratio compared, from {crossover:,.0f}:1 up"
                else:
                    summary = f"networks ahead of {name} from {crossover:,.0f}:1 up"
                for label, wanted in (("ahead at", True), ("behind at", False)):
                    ratios = [f"{ratio:,.0f}" for ratio, ahead in verdicts if ahead == wanted]
                    if ratios:
                        summary += f"; {label} {', '.join(ratios)}:1"
            lines.append(f"| {dataset} | crossover | | | {name} | | {summary} |")
    return lines


def _with_spread(summary: Summary, digits: int) -> str:
    if not math.isfinite(summary.mean):
        return "nan"
    if summary.count > 1:
        return f"{summary.mean:.{digits}f} ± {summary.std:.{digits}f}"
    return f"{summary.mean:.{digits}f}"


def _ratio_text(stored: float, float32: float) -> str:
    """``"9.9"``, or ``"9.9 (39.6)"`` with the float32 ratio where the volume is stored in another dtype."""
    return f"{stored:.1f}" if math.isclose(stored, float32) else f"{stored:.1f} ({float32:.1f})"


def _kilobytes(count: int) -> str:
    return f"{count / 1024:,.1f} KB" if count < 10 * 1024**2 else f"{count / 1024**2:,.1f} MB"


def _protocol(rows: list[QualityRow]) -> str:
    """One sentence naming the budgets, seeds and devices the rows came from."""
    budgets = sorted({(r.iterations, r.batch_size) for r in rows})
    seeds = sorted({len(g) for g in group_quality(rows).values()})
    devices = sorted({r.device for r in rows})
    schedules = sorted({f"{MODEL_TITLES.get(r.model, r.model)} {r.lr_schedule}" for r in rows})
    voxels = sorted({f"{MODEL_TITLES.get(r.model, r.model)} {r.voxel_fraction:g}" for r in rows})
    budget_text = ", ".join(f"{i:,} iterations x {b:,} points" for i, b in budgets)
    seed_text = "/".join(str(s) for s in seeds)
    return (
        f"Protocol: {budget_text}; {seed_text} seed(s) per cell; learning-rate schedule "
        f"{', '.join(schedules)}; share of voxel points {', '.join(voxels)}; device {', '.join(devices)}."
    )
