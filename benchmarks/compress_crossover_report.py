"""Issue 15's crossover page from `apmgsrn bench compress` CSVs: for each volume the rate-distortion table,
every network on the frontier against SZ3 and ZFP at the same ratio with the crossover ratio, and the chart.

    bash benchmarks/compress_crossover.sh DATA VARIABLE MAX_ERROR OUT          # per volume, see that script
    python benchmarks/compress_crossover_report.py hcci=OUT1/compress_*.csv miranda=OUT2/compress_*.csv \
        --out docs/results_compress_crossover.md                            # charts go to docs/images/

NAME=CSV1,CSV2 joins the rows of several runs of one volume (compressors measured apart from the networks,
`apmgsrn bench compress DATA --models --compressors zfp-precision`); the kept CSV holds them all.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from apmgsrn.bench.charts import rate_distortion_chart  # noqa: E402
from apmgsrn.bench.results import CompressRow, read_rows, write_rows  # noqa: E402
from apmgsrn.bench.tables import compress_table, crossover_lines  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="NAME=CSV[,CSV...]")
    parser.add_argument("--out", required=True, help="markdown page to write")
    parser.add_argument("--keep-csv", default=str(REPO / "benchmarks" / "results"),
                        help="folder that keeps a copy of each CSV (compress_crossover_NAME.csv)")
    args = parser.parse_args()
    out = Path(args.out)
    images = out.parent / "images"
    images.mkdir(parents=True, exist_ok=True)
    summary, sections = [], []
    for run in args.runs:
        name, _, csvs = run.partition("=")
        rows = [row for csv in csvs.split(",") for row in read_rows(Path(csv), CompressRow)]
        write_rows(Path(args.keep_csv) / f"compress_crossover_{name}.csv", rows, CompressRow)
        chart = images / f"compress_crossover_{name}.png"
        rate_distortion_chart(rows, chart, title=rows[0].dataset)
        for line in crossover_lines(rows):
            cells = [cell.strip() for cell in line.strip("|").split("|")]
            if len(cells) == 7 and cells[1] == "crossover":
                summary.append(f"| {cells[0]} | {cells[4]} | {cells[6]} |")
        sections += [f"## {rows[0].dataset}", "", f"![rate-distortion, {name}](images/{chart.name})", "",
                     compress_table(rows), ""]
    text = "\n".join([
        "# Networks against SZ3 and ZFP, from 10:1 to 10,000:1 (issue 15)", "",
        "Made by `bash benchmarks/compress_crossover.sh DATA VARIABLE MAX_ERROR OUT` per volume (a small model, "
        "APMGSRN and the default hybrid, "
        "2,000 iterations x 32,768 points, CPU, seed 0, each packed at the default 0.1 dB budget, at 1,000:1 and "
        "3,000:1, and bounded at about 4 % of the value range at 1,000:1; APMGSRN models that `train --ratio` sizes "
        "for 300:1, 1,000:1, 3,000:1 and 10,000:1 (grids, decoder and resolution chosen for the target, one "
        "grid anchored; docs/packing.md), where one fits; SZ3 and ZFP at relative bounds 0.5 ... 0.001, and ZFP in "
        "fixed-precision mode at 1-8 bit planes, the mode that reaches 100-200:1 where the accuracy mode stops "
        "near 30:1), then "
        "`python benchmarks/compress_crossover_report.py "
        f"NAME=CSV ... --out {out.as_posix()}`. One seed. Ratios against the stored bytes (a uint8 volume "
        "counts one byte per voxel; the float32 ratio is in parentheses in the tables). The CSVs are kept in "
        "benchmarks/results/compress_crossover_*.csv.", "",
        "Crossover per volume (the lowest ratio from which every network on the frontier that could be "
        "compared is ahead):", "",
        "| volume | compressor | crossover |", "|---|---|---|", *summary, "",
        *sections,
    ])
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
