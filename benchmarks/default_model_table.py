"""The default model against the best other model per volume, from ``bench quality`` CSVs (issue 14's table).

    python benchmarks/default_model_table.py --model hybrid --size small \
        benchmarks/results/default_quality_small*.csv benchmarks/results/baselines_quality*.csv

Per volume: the model's mean PSNR over its seeds (± standard deviation), the best mean of every other model
kind in the CSVs, the difference, largest errors and stored bytes. Prints a Markdown table (docs/models.md).

With ``--compare LABEL=CSV[,CSV...]`` (repeatable) it prints instead one column per label: the ``--model``
rows' mean PSNR ± spread in those files, per volume (an ablation: one variant per label).
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
from collections import defaultdict
from pathlib import Path

from apmgsrn.bench.results import MODEL_TITLES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("csv", nargs="*", type=Path)
    parser.add_argument("--model", default="hybrid")
    parser.add_argument("--size", default="small")
    parser.add_argument("--margin", type=float, default=0.3, help="lead the issue asks for (dB)")
    parser.add_argument("--compare", action="append", default=[], metavar="LABEL=CSV[,CSV]")
    args = parser.parse_args()
    if args.compare:
        compare(args)
        return
    groups = read_groups(args.csv, args.size)
    datasets = list(dict.fromkeys(dataset for dataset, model in groups if model == args.model))
    print(f"| volume | {args.model} {args.size} (mean ± sd, seeds) | best other (mean, seeds) | difference | "
          f"max error ({args.model} / other) | stored bytes ({args.model} / other) | file bytes |")
    print("|---|---|---|---|---|---|---|")
    held = 0
    for dataset in datasets:
        ours = groups[(dataset, args.model)]
        others = {model: rows for (d, model), rows in groups.items() if d == dataset and model != args.model}
        if not others:
            continue
        best_model, best = max(others.items(), key=lambda item: statistics.fmean(r.psnr for r in item[1]))
        mean = statistics.fmean(r.psnr for r in ours)
        spread = statistics.stdev(r.psnr for r in ours) if len(ours) > 1 else 0.0
        other = statistics.fmean(r.psnr for r in best)
        difference = mean - other
        held += difference >= args.margin
        error = _mean_finite([r.max_abs_error for r in ours])
        other_error = _mean_finite([r.max_abs_error for r in best])
        print(f"| {dataset} {ours[0].shape} | {mean:.2f} ± {spread:.2f} ({len(ours)}) | "
              f"{MODEL_TITLES.get(best_model, best_model)} {other:.2f} ({len(best)}) | {difference:+.2f} | "
              f"{_number(error)} / {_number(other_error)} | {ours[0].parameter_bytes:,} / "
              f"{best[0].parameter_bytes:,} | {ours[0].file_bytes:,} / {best[0].file_bytes:,} |")
    print(f"\n{held} of {len(datasets)} volumes at least {args.margin} dB ahead.")


def read_groups(paths: list[Path], size: str) -> dict[tuple[str, str], list["Row"]]:
    """Rows of one size by (dataset, model), from CSVs of any version (older files lack some columns)."""
    groups: dict[tuple[str, str], list[Row]] = defaultdict(list)
    for path in paths:
        with open(path, newline="") as handle:
            for record in csv.DictReader(handle):
                if record["size"] == size:
                    groups[(record["dataset"], record["model"])].append(Row(record))
    return groups


def compare(args) -> None:
    """One column per ``--compare`` label: mean PSNR ± spread (seeds) of the ``--model`` rows per volume."""
    labels, tables = [], []
    for text in args.compare:
        label, _, paths = text.partition("=")
        labels.append(label)
        tables.append(read_groups([Path(p) for p in paths.split(",")], args.size))
    datasets = list(dict.fromkeys(d for table in tables for d, m in table if m == args.model))
    print("| volume | " + " | ".join(labels) + " |")
    print("|---|" + "---|" * len(labels))
    for dataset in datasets:
        cells = []
        for table in tables:
            rows = table.get((dataset, args.model), [])
            if not rows:
                cells.append("–")
                continue
            spread = statistics.stdev(r.psnr for r in rows) if len(rows) > 1 else 0.0
            cells.append(f"{statistics.fmean(r.psnr for r in rows):.2f} ± {spread:.2f} ({len(rows)})")
        print(f"| {dataset} | " + " | ".join(cells) + " |")


class Row:
    """The columns used here of one ``bench quality`` CSV row."""

    def __init__(self, record: dict):
        self.shape = record["shape"]
        self.psnr = float(record["psnr"])
        self.max_abs_error = float(record.get("max_abs_error") or "nan")
        self.parameter_bytes = int(record["parameter_bytes"])
        self.file_bytes = int(record["file_bytes"])


def _mean_finite(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return statistics.fmean(finite) if finite else math.nan


def _number(value: float) -> str:
    return "–" if not math.isfinite(value) else f"{value:.4g}"


if __name__ == "__main__":
    main()
