"""Stepwise steps whose grid placement moves too: a prototype measurement for series whose structures travel.

    python benchmarks/bench_series_moving_placement.py --data DIR --csv benchmarks/results/time_series_moving_placement.csv

``DIR`` holds one volume file per step (``bench_time_series.py moving --out DIR`` writes a real volume shifted
further at every step). It trains as ``apmgsrn train`` does on a series (a small model of the start step the
data choose, 2,000 iterations x 32,768 points, half of each batch on voxels, one anchored grid, seed 0; every
other step fine-tuned from its neighbour with the adaptive budget of
:meth:`~apmgsrn.series.steps.StepwiseConfig.step_config`), with one difference: during each step's
fine-tune the feature-density loss moves that step's grid placement as well (from its first iteration, frozen
at half of the fine-tune as for one volume), so every step has its own placement. The decoder stays shared.
Not a product path: each step's network is measured (PSNR over every voxel, float32) as it is trained, and
nothing is stored.
"""

from __future__ import annotations

import argparse
import csv
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from apmgsrn.data.readers import SUPPORTED_SUFFIXES
from apmgsrn.series.data import open_series
from apmgsrn.inference.evaluate import evaluate
from apmgsrn.models.registry import preset_config
from apmgsrn.training.fit import prepare_values, train_prepared
from apmgsrn.series.steps import (StepwiseConfig, change, change_factor,
                                           choose_start, step_order)
from apmgsrn.recipes import SERIES
from apmgsrn.training.trainer import TrainConfig, Trainer


def load_series_folder(folder: Path):
    """The steps of a folder of volume files (name order) as ``[T, D, H, W]`` data units, and prepared for training."""
    suffixes = {s for names in SUPPORTED_SUFFIXES.values() for s in names}
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in suffixes)
    data = open_series([str(f) for f in files]).to_numpy()  # [T, D, H, W]
    return data, prepare_values(data, "none", 0.0, str(folder), torch.device("cpu"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a folder of volume files, one per step")
    parser.add_argument("--csv", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    data, prepared = load_series_folder(args.data)
    config = TrainConfig(iterations=2000, voxel_fraction=SERIES.voxel_fraction, anchored_grids=SERIES.anchored_grids,
                         seed=args.seed)
    began = time.perf_counter()
    start = choose_start(prepared.values, "auto")
    first = train_prepared(replace(prepared, values=prepared.values[start]), preset_config("apmgsrn", "small"),
                           config, tuple(data.shape[1:]), None, {}, [])
    field = first.field
    error = float(np.sqrt(first.state.history["reconstruction"][-1]))
    states = {start: {k: v.clone() for k, v in field.state_dict().items()}}
    rows = [{"step": start, "psnr": evaluate(field.eval(), data[start]).psnr, "iterations": 0}]
    print(rows[-1], flush=True)
    for parameter in field.decoder.parameters():
        parameter.requires_grad_(False)
    for step, neighbour in step_order(start, len(data)):
        field.load_state_dict(states[neighbour])
        for parameter in field.encoder.placement_parameters():
            parameter.requires_grad_(True)  # the trainer freezes them at half of each fine-tune
        factor = change_factor(change(prepared.values, step, neighbour), error)
        step_config = StepwiseConfig().step_config(config, factor)
        Trainer(field.train(), prepared.values[step], replace(step_config, density_start=0), None, {}, []).run()
        states[step] = {k: v.clone() for k, v in field.state_dict().items()}
        rows.append({"step": step, "psnr": evaluate(field.eval(), data[step]).psnr,
                     "iterations": step_config.iterations})
        print(rows[-1], flush=True)
    print(f"{time.perf_counter() - began:.0f} s", flush=True)
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with args.csv.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, ["step", "psnr", "iterations"])
        writer.writeheader()
        writer.writerows(sorted(rows, key=lambda row: row["step"]))


if __name__ == "__main__":
    main()
