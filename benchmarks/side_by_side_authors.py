"""Time per training iteration of this project's models beside the authors' code, in one run.

The authors' public implementation (skywolf829/APMGSRN, commit ab83249) is not part of this project: pass a
checkout of it with ``--authors``. Their ``Code/train.py`` runs unchanged in a child process from a temporary
copy (its ``Data/`` holds a link to the volume; the TensorBoard import, unused with ``--log_every 0``, is given a
placeholder module so that the package need not be installed, and their ``ReduceLROnPlateau(verbose=True)``, an
argument torch 2.13 no longer takes, has it dropped). Every run is a fresh process; each round runs
every method at every iteration count, in an order that alternates between rounds so that load on a shared
machine falls on all alike. A method's time per iteration is the difference of its two runs' training times
divided by the difference of their iterations (setup and the first iterations' warm-up cancel out); the table
gives the median over rounds and the ratio to the authors'.

Their time is the one their ``train`` prints (its data loader's point draws included); ours is the one
``apmgsrn train`` records (``info --json``: training.seconds, point draws included). Small preset, 32,768 points
an iteration, lr 0.01, the same threads for both.

    python benchmarks/side_by_side_authors.py --authors /path/to/APMGSRN \\
        --volume ../shared/data/hcci_oh_187.nc:oh --rounds 3 --out docs/benchmarks_side_by_side.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PRELUDE = """
import runpy, sys, types
placeholder = types.ModuleType("torch.utils.tensorboard")
placeholder.SummaryWriter = None
sys.modules["torch.utils.tensorboard"] = placeholder
import torch.optim.lr_scheduler as schedulers
class Plateau(schedulers.ReduceLROnPlateau):
    def __init__(self, *args, verbose=None, **kwargs):
        super().__init__(*args, **kwargs)
schedulers.ReduceLROnPlateau = Plateau
sys.path.insert(0, {code!r})
sys.argv = [{script!r}] + {argv!r}
runpy.run_path({script!r}, run_name="__main__")
"""
DONE = re.compile(r"Model completed training after (\d+)m ([0-9.]+)s")
METHODS = ("authors", "hybrid", "apmgsrn")


def authors_seconds(code: Path, volume: Path, iterations: int, batch: int) -> float:
    """The authors' training time (seconds) for ``iterations`` of their small preset (their reader takes the
    file's first variable)."""
    argv = ["--model", "APMGSRN", "--n_grids", "16", "--n_features", "1", "--feature_grid_shape", "16,16,16",
            "--n_layers", "2", "--nodes_per_layer", "64", "--iterations", str(iterations),
            "--points_per_iteration", str(batch), "--lr", "0.01", "--device", "cpu", "--data_device", "cpu",
            "--use_tcnn_if_available", "false", "--log_every", "0", "--data", volume.name,
            "--save_name", f"side_by_side_{iterations}"]
    script = str(code / "train.py")
    prelude = PRELUDE.format(code=str(code), script=script, argv=argv)
    out = subprocess.run([sys.executable, "-c", prelude], cwd=code, capture_output=True, text=True)
    found = DONE.search(out.stdout)
    if out.returncode != 0 or found is None:
        raise SystemExit(f"the authors' train.py failed (rc {out.returncode}):\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}")
    return int(found.group(1)) * 60 + float(found.group(2))


def own_seconds(kind: str, volume: Path, variable: str | None, iterations: int, batch: int, work: Path) -> float:
    """This project's training time (seconds) for ``iterations`` of ``kind``'s small preset."""
    model = work / f"{kind}_{iterations}_{time.monotonic_ns()}.apmgsrn"
    exe = [sys.executable, "-m", "apmgsrn"]
    named = ["--variable", variable] if variable else []
    run = subprocess.run(exe + ["train", str(volume), *named, "--model", kind, "--preset", "small", "--iterations", str(iterations),
                                "--batch-size", str(batch), "--out", str(model)],
                         capture_output=True, text=True)
    if run.returncode != 0:
        raise SystemExit(f"apmgsrn train failed (rc {run.returncode}): {run.stderr.strip()[-2000:]}")
    info = subprocess.run(exe + ["info", str(model), "--json"], capture_output=True, text=True, check=True)
    return float(json.loads(info.stdout)["training"]["seconds"])


def prepare_authors(checkout: Path, volume: Path, into: Path) -> Path:
    """A private copy of the authors' ``Code`` folder with ``Data/`` linking to ``volume``; returns ``Code``."""
    if not (checkout / "Code" / "train.py").is_file():
        raise SystemExit(f"--authors {checkout}: not a checkout of skywolf829/APMGSRN (no Code/train.py)")
    shutil.copytree(checkout / "Code", into / "Code")
    for folder in ("Data", "SavedModels", "Output"):
        (into / folder).mkdir()
    (into / "Data" / volume.name).symlink_to(volume.resolve())
    return into / "Code"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--authors", type=Path, required=True, help="a checkout of skywolf829/APMGSRN")
    parser.add_argument("--volume", required=True, help="FILE[:VARIABLE], a NetCDF volume both codes read")
    parser.add_argument("--iterations", type=int, nargs=2, default=(200, 700))
    parser.add_argument("--batch-size", type=int, default=32768)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--out", type=Path, help="Markdown file for the table")
    args = parser.parse_args()
    path = Path(args.volume.split(":")[0])
    variable = args.volume.split(":")[1] if ":" in args.volume else None
    low, high = sorted(args.iterations)
    seconds: dict[tuple[str, int], list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        code = prepare_authors(args.authors, path, work / "authors")
        for round_ in range(args.rounds):
            order = [(m, n) for m in args.methods for n in (low, high)]
            if round_ % 2:
                order.reverse()
            for method, n in order:
                start = time.perf_counter()
                if method == "authors":
                    s = authors_seconds(code, path, n, args.batch_size)
                else:
                    s = own_seconds(method, path, variable, n, args.batch_size, work)
                seconds.setdefault((method, n), []).append(s)
                print(f"round {round_ + 1}: {method:8s} {n:5d} iterations {s:8.2f} s "
                      f"(process {time.perf_counter() - start:.1f} s)", flush=True)
    per_it = {m: [1000 * (b - a) / (high - low) for a, b in zip(seconds[(m, low)], seconds[(m, high)])]
              for m in args.methods}
    median = {m: statistics.median(v) for m, v in per_it.items()}
    threads = os.environ.get("OMP_NUM_THREADS", "torch default")
    lines = [f"Volume `{path.name}`, {args.batch_size:,} points an iteration, small preset, ({high} - {low}) iterations, "
             f"{args.rounds} rounds; {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
             f"OMP_NUM_THREADS={threads}, {time.strftime('%Y-%m-%d')}.", "",
             "| method | ms / iteration (median) | each round | vs the authors' code |", "|---|---:|---|---:|"]
    for m in args.methods:
        ratio = f"{median[m] / median['authors']:.2f}" if "authors" in median else "-"
        rounds = ", ".join(f"{v:.1f}" for v in per_it[m])
        lines.append(f"| {m} | {median[m]:.1f} | {rounds} | {ratio} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
