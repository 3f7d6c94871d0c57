"""Charts of benchmark results (matplotlib, imported only when a chart is drawn; no pyplot state)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

from apmgsrn.atomic import atomic_write
from apmgsrn.bench.results import MODEL_TITLES, SIZE_ORDER, CompressRow, QualityRow, Summary, group_quality, ordered
from apmgsrn.choices import MODEL_KINDS

# One colour per method, the same in every chart.
COLOURS = {"apmgsrn": "#d62728", "fvsrn": "#1f77b4", "ngp": "#2ca02c", "hybrid": "#17becf", "sz3": "#9467bd",
           "zfp": "#ff7f0e", "zfp-precision": "#ffbb78", "sperr": "#7f7f7f", "sperr-pwe": "#c7c7c7",
           "tthresh": "#000000", "apmgsrn packed": "#8c564b",
           "apmgsrn packed bounded": "#e377c2", "hybrid packed": "#0b6e79", "hybrid packed bounded": "#bcbd22"}
MARKERS = {"small": "o", "medium": "s", "large": "D"}


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def quality_chart(rows: list[QualityRow], path: Path) -> None:
    """Grouped bars of mean PSNR per volume and model, one panel per size; whiskers: seed std.

    Args:
        rows: results of ``bench quality``.
        path: PNG file to write.
    """
    groups = group_quality(rows)
    datasets = list(dict.fromkeys(r.dataset for r in rows))
    models = ordered((r.model for r in rows), MODEL_KINDS)
    sizes = ordered((r.size for r in rows), SIZE_ORDER)
    # Sizes side by side while the volumes are few, one above the other when a row would grow too wide.
    panel_rows, panel_columns = (len(sizes), 1) if len(datasets) * len(sizes) > 8 else (1, len(sizes))
    figure = _figure(max(6.0, 1.3 * len(datasets) * panel_columns), 3.6 * panel_rows)
    axes = figure.subplots(panel_rows, panel_columns, squeeze=False).ravel()
    width = 0.8 / len(models)
    for axis, size in zip(axes, sizes):
        for j, model in enumerate(models):
            xs, means, spreads = [], [], []
            for i, dataset in enumerate(datasets):
                group = groups.get((dataset, model, size))
                if not group:
                    continue
                summary = Summary.of([r.psnr for r in group])
                xs.append(i + (j - (len(models) - 1) / 2) * width)
                means.append(summary.mean)
                spreads.append(summary.std if summary.count > 1 else 0.0)
            # Whiskers only where several seeds give a spread to show.
            axis.bar(xs, means, width, yerr=spreads if any(spreads) else None, capsize=2, color=COLOURS.get(model),
                     label=MODEL_TITLES.get(model, model))
        axis.set_xticks(range(len(datasets)))
        axis.set_xticklabels([d.split(".")[0] for d in datasets], rotation=30, ha="right", fontsize=8)
        axis.set_title(f"{size} models")
        axis.set_ylabel("PSNR (dB)")
        finite = [r.psnr for r in rows if r.size == size and math.isfinite(r.psnr)]
        if finite:
            axis.set_ylim(max(0.0, min(finite) - 5), max(finite) + 2)
        axis.grid(axis="y", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="outside upper center", ncols=len(models), fontsize=8)
    atomic_write(path, figure.savefig, "chart")


def rate_distortion_chart(rows: list[CompressRow], path: Path, title: str = "",
                          ratio_label: str = "compression ratio (stored bytes / compressed bytes)") -> None:
    """PSNR against compression ratio (log scale): a line per compressor, a point per network.

    Args:
        rows: results of ``bench compress`` for one volume.
        path: PNG file to write.
        title: chart title (the volume).
        ratio_label: the x axis' title: what ``compression_ratio`` of the rows is against.
    """
    figure = _figure(6.4, 4.2)
    axis = figure.subplots()
    methods = list(dict.fromkeys(r.method for r in rows))
    for method in methods:
        points = sorted((r for r in rows if r.method == method), key=lambda r: r.compression_ratio)
        label = MODEL_TITLES.get(method, method.upper())
        exact = [r for r in points if not math.isfinite(r.psnr)]
        if exact:
            # An exact reconstruction has no PSNR to plot: say so in the legend instead.
            ratios = ", ".join(f"{r.compression_ratio:.1f}" for r in exact)
            label += f" (exact at ratio {ratios})"
            points = [r for r in points if math.isfinite(r.psnr)]
            if not points:
                axis.plot([], [], "-o", markersize=3, color=COLOURS.get(method), label=label)
                continue
        if method in MODEL_TITLES:
            for r in points:
                axis.scatter(r.compression_ratio, r.psnr, color=COLOURS.get(method), s=45, zorder=3,
                             marker=MARKERS.get(r.setting, "o"), label=f"{label} {r.setting}")
        elif method.split()[0] in MODEL_TITLES:
            # Packed or bounded networks: a line per setting, so that one model packed harder and models sized
            # for each ratio ("custom") are not joined into one zigzag.
            for index, setting in enumerate(dict.fromkeys(r.setting for r in points)):
                same = [r for r in points if r.setting == setting]
                axis.plot([r.compression_ratio for r in same], [r.psnr for r in same], ("-o", "--s", ":^")[index % 3],
                          markersize=4, color=COLOURS.get(method), label=f"{label} {setting}")
        else:
            axis.plot([r.compression_ratio for r in points], [r.psnr for r in points], "-o", markersize=3,
                      color=COLOURS.get(method), label=label)
    axis.set_xscale("log")
    axis.set_xlabel(ratio_label)
    axis.set_ylabel("PSNR (dB)")
    axis.set_title(title)
    axis.grid(alpha=0.3, which="both")
    axis.legend(fontsize=8)
    atomic_write(path, figure.savefig, "chart")


def psnr_over_time_chart(labels: list[float], lines: dict[str, list[float]], path: Path, title: str = "") -> None:
    """PSNR of every step of a time series, one line per method (e.g. one model per step against one model for
    the whole series).

    Args:
        labels: the step numbers (x axis).
        lines: method name -> PSNR of each step, dB (NaN where a method has no figure: its line joins the
            steps it has).
        path: PNG file to write.
        title: the chart's title.
    """
    figure = _figure(6.4, 3.4 + 0.17 * len(lines))  # the legend sits below the axes, one entry a row
    axis = figure.subplots()
    for (name, values), marker in zip(lines.items(), itertools.cycle("os^Dv")):
        measured = [(x, y) for x, y in zip(labels, values) if math.isfinite(y)]
        axis.plot([x for x, _ in measured], [y for _, y in measured], marker=marker, markersize=3.5, linewidth=1.2,
                  label=name)
    if all(float(x).is_integer() for x in labels):
        from matplotlib.ticker import MaxNLocator

        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.set_xlabel("time step")
    axis.set_ylabel("PSNR (dB)")
    if title:
        axis.set_title(title, fontsize=10)
    axis.grid(alpha=0.3)
    figure.legend(fontsize=7, loc="outside lower center")
    atomic_write(path, figure.savefig, "chart")
