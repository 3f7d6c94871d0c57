"""A time budget: the iterations this machine trains in the minutes a user states (``train --minutes``).

The cost of an iteration depends on the model, the batch, the device, the threads and the load, so it is
measured, not modelled: a throwaway copy of the run's field takes a few real steps in each phase of the
loop (grids moving, with the density step; grids frozen), and the budget is spread over the two phases in the
shares the schedule gives them (the grids move until ``freeze_fraction`` of the budget at the latest). The
iteration count then replaces the plan's, before training starts, so the learning-rate schedule and the
freeze fit the budget exactly as they would a count given by hand. The probe's own seconds and the final
evaluation (and packing) are not part of the budget; the report says what was measured.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, replace

import torch

from apmgsrn.arguments import MAX_ITERATIONS, check_number
from apmgsrn.errors import ApmgsrnError
from apmgsrn.limits import LIMITS
from apmgsrn.recipes import RUNTIME
from apmgsrn.io.container import read_header
from apmgsrn.training.trainer import TrainConfig, Trainer

@dataclass(frozen=True)
class TimeBudget:
    """What sizing a run for its minutes measured and chose.

    Attributes:
        minutes: the budget asked.
        moving_seconds, frozen_seconds: median seconds of one iteration with the grids moving and frozen.
        seconds_per_iteration: their mean over the schedule's phases.
        iterations: the iterations that fill the budget.
    """

    minutes: float
    moving_seconds: float
    frozen_seconds: float
    seconds_per_iteration: float
    iterations: int

    def to_dict(self) -> dict:
        return {"minutes": self.minutes, "seconds_per_iteration": round(self.seconds_per_iteration, 6),
                "moving_seconds": round(self.moving_seconds, 6), "frozen_seconds": round(self.frozen_seconds, 6),
                "iterations": self.iterations}

    def line(self) -> str:
        """One line for the log: what was measured and what it gives."""
        return (f"time budget {self.minutes:g} min: {1000 * self.seconds_per_iteration:.1f} ms an iteration "
                f"measured ({1000 * self.moving_seconds:.1f} with the grids moving, "
                f"{1000 * self.frozen_seconds:.1f} frozen) -> {self.iterations:,} iterations")


def median_step_seconds(trainer: Trainer, least_seconds: float, least_steps: int, most_steps: int) -> float:
    """Median seconds of the trainer's steps from its current state: at least ``least_steps`` and
    ``least_seconds`` of them, at most ``most_steps`` (a GPU is synchronised around each)."""
    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    times: list[float] = []
    started = time.perf_counter()
    while len(times) < most_steps and (len(times) < least_steps or time.perf_counter() - started < least_seconds):
        sync()
        start = time.perf_counter()
        trainer.step()
        sync()
        trainer.state.iteration += 1
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def size_for_minutes(field, values: torch.Tensor, train_config: TrainConfig, minutes: float,
                     probe_seconds: float = RUNTIME.budget_probe_seconds) -> tuple[TrainConfig, TimeBudget]:
    """``train_config`` with the iterations that fill ``minutes`` of training on this machine (module docstring).

    Args:
        field: a throwaway field of the run's model (the probe trains it; the run builds its own).
        values: the run's fitted values, on the run's device.
        train_config: the run's settings; only ``iterations`` and ``density_start`` (the same share of them)
            change.
        minutes: the budget.
        probe_seconds: least seconds each phase is timed for (after one warm-up step).

    Raises:
        InvalidArgument: ``minutes`` not in ``(0, LIMITS.minutes]``.
    """
    check_number("minutes", minutes, 0.0, LIMITS.minutes, low_open=True)
    trainer = Trainer(field, values, train_config)
    trainer.state.iteration = train_config.density_start  # the grids move from here
    median_step_seconds(trainer, 0.0, 1, 1)  # warm-up: kernels built, buffers allocated
    moving = median_step_seconds(trainer, probe_seconds, *RUNTIME.budget_probe_steps)
    trainer.state.frozen_at = trainer.state.iteration
    for parameter in field.encoder.placement_parameters():
        parameter.requires_grad_(False)
    frozen = median_step_seconds(trainer, probe_seconds, *RUNTIME.budget_probe_steps)
    moving_share = train_config.freeze_fraction if field.encoder.placement_parameters() else 0.0
    per_iteration = moving_share * moving + (1 - moving_share) * frozen
    iterations = min(max(1, math.floor(minutes * 60 / per_iteration)), MAX_ITERATIONS)
    share = train_config.density_start / train_config.iterations
    sized = replace(train_config, iterations=iterations, density_start=min(iterations, round(share * iterations)))
    return sized, TimeBudget(minutes, moving, frozen, per_iteration, iterations)


def resumed_budget(checkpoint, train_config: TrainConfig) -> TrainConfig:
    """``train_config`` with the iterations (and density start) an interrupted run of a time budget chose, read
    from its checkpoint, so that the resume continues the same schedule instead of measuring again.

    Raises:
        ApmgsrnError: the checkpoint is unreadable or records no budget.
    """
    recorded = read_header(checkpoint).description.get("config")
    iterations = recorded.get("iterations") if isinstance(recorded, dict) else None
    density_start = recorded.get("density_start") if isinstance(recorded, dict) else None
    if not (isinstance(iterations, int) and isinstance(density_start, int)):
        raise ApmgsrnError(f"{checkpoint}: records no training budget to resume; start the run again instead "
                           "of resuming it", arguments=("resume",))
    return replace(train_config, iterations=iterations, density_start=density_start)
