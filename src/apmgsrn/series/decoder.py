"""The shared decoder of a packed stepwise series fine-tuned to the grids the file stores.

A stepwise series (:mod:`apmgsrn.series.steps`) keeps the start model's decoder frozen while every other
step's grids are fitted to it, and the packing then rounds those grids (:mod:`apmgsrn.series.packing`).
The decoder has seen neither the other steps nor the rounded values. Here, once the file's integers are fixed,
the decoder alone is trained a little on all steps at once, every step's grids held at what the file gives back.
The decoder is stored exactly (float32), so this costs no byte, and the integers stay the same.

Every iteration draws ``PACKING.decoder_steps_per_iteration`` steps at random and a share of the start model's batch
on each. The loss weights each step by one over its error before the fine-tune, so that every step's PSNR counts
alike: a decoder trained on the plain sum would serve the steps with the largest errors, which the steps that fit
closest (and are nearest to falling below their own models) would pay for. Should the fine-tune not lower that
weighted error on a fixed sample of every step's voxels, the decoder is put back as it was.

Measured on trained, packed hybrid series (docs/time_series.md), 300 iterations with a tenth of their points
between the voxels (``PACKING.decoder_voxel_fraction``), about 10 s on two threads: the steps least like the start
model's gain most (t010 of three steps 40 apart +0.59 dB, step 0 of the 30 viscous-finger steps at 128^3 +0.08,
the first steps of their crop to half the height +0.19), the others little (the 30 steps at 64^3 -0.03 to +0.06), and
between the voxels no step moves by more than 0.05 dB. Its time is not taken from the steps' budget: shortening
their fine-tunes by as many points (at 1.5 fine-tune points each) cost the 30 steps 0.13-0.72 dB (mean 0.32).
"""

from __future__ import annotations

import time

import torch

from apmgsrn.series.field import SeriesField
from apmgsrn.progress import Progress
from apmgsrn.recipes import PACKING
from apmgsrn.training.points import draw_batch
from apmgsrn.series.steps import check_sample
from apmgsrn.training.trainer import TrainConfig


def fine_tune_decoder(series: SeriesField, values: torch.Tensor, config: TrainConfig, iterations: int,
                      show_progress: bool = True) -> tuple[int, float]:
    """The series' decoder trained on every step with its grids and placement frozen (module docstring); the
    field is changed in place, and left as it was when the fine-tune did not help.

    Args:
        series: a trained series field holding what its packed file gives back.
        values: ``[T, D, H, W]`` the training values.
        config: the start model's training: its batch (split over the steps drawn), learning rate (times
            ``PACKING.decoder_lr_share``) and seed.
        iterations: the fine-tune's iterations.
        show_progress: one line of progress over the iterations.

    Returns:
        (iterations run: 0 when the decoder was put back or nothing ran, seconds).
    """
    began = time.perf_counter()
    steps = values.shape[0]
    if iterations < 1:
        return 0, 0.0
    checks = [check_sample(values[t], t) for t in range(steps)]
    before = torch.tensor([_step_error(series, t, check) for t, check in enumerate(checks)])
    if not bool((before > 0).all()):
        return 0, time.perf_counter() - began  # a step fitted exactly: nothing to weigh the others against
    weights = before.reciprocal() / before.reciprocal().mean()
    kept = {name: p.detach().clone() for name, p in series.decoder.state_dict().items()}
    trainable = [p.requires_grad for p in series.parameters()]
    series.requires_grad_(False)
    series.decoder.requires_grad_(True)
    drawn = min(PACKING.decoder_steps_per_iteration, steps)
    batch = max(1, config.batch_size // drawn)
    generator = torch.Generator(values.device).manual_seed(config.seed)  # the points
    chooser = torch.Generator().manual_seed(config.seed)  # the steps
    optimizer = torch.optim.Adam(series.decoder.parameters(), lr=config.lr * PACKING.decoder_lr_share)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, iterations)
    try:
        with Progress(iterations, unit="it", description="decoder", enabled=show_progress) as shown:
            for _ in range(iterations):
                chosen = torch.randperm(steps, generator=chooser)[:drawn]
                points, targets = zip(*(draw_batch(values[t], batch, PACKING.decoder_voxel_fraction, generator)
                                        for t in chosen.tolist()))
                predicted = series.normalized(torch.cat(points), chosen.to(values.device)).view(drawn, batch)
                errors = (predicted - torch.stack(targets)).square().mean(dim=1)
                loss = (errors * weights[chosen].to(errors.device)).mean()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                schedule.step()
                shown.update(1)
    finally:
        for parameter, flag in zip(series.parameters(), trainable):
            parameter.requires_grad_(flag)
    after = torch.tensor([_step_error(series, t, check) for t, check in enumerate(checks)])
    if float((after / before).mean()) >= 1.0:
        series.decoder.load_state_dict(kept)
        return 0, time.perf_counter() - began
    return iterations, time.perf_counter() - began


@torch.no_grad()
def _step_error(series: SeriesField, step: int, check: tuple[torch.Tensor, torch.Tensor]) -> float:
    """Mean squared error of step ``step`` at the ``(points, targets)`` of its check sample."""
    points, targets = check
    index = torch.tensor([step], device=points.device)
    return float((series.normalized(points, index).view(-1) - targets).square().mean())
