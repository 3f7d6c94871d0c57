"""Training checkpoints (``MODEL.ckpt``): the whole state of an unfinished run, so it resumes exactly.

A checkpoint is a :mod:`apmgsrn.io.container` file of kind ``training-state``: the field's tensors, the
optimisers' moments and the random generator's state, plus a JSON description (run fingerprint, config,
loop state). Written atomically: a kill at any moment leaves the previous one.

A checkpoint is read as untrusted input, like a model file: the loop state is checked field by field
(:func:`state_from_json`) and every tensor against the name, shape and dtype the run expects
(:func:`check_tensors`) before anything is loaded into the field or the optimisers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path

import torch

from apmgsrn.io.description import DescriptionError, require_dict, require_int, require_number

CHECKPOINT_KIND = "training-state"
#: Keys of one parameter's Adam state (no AMSGrad).
ADAM_STATE = ("exp_avg", "exp_avg_sq", "step")
HISTORY_KEYS = ("iteration", "reconstruction", "density", "lr")


def checkpoint_path_for(model_path: str | Path) -> Path:
    """The training checkpoint beside a model file (``MODEL.ckpt``)."""
    return Path(str(model_path) + ".ckpt")


@dataclass
class TrainingState:
    """Everything besides tensors that a resumed run needs (saved as JSON in the checkpoint)."""

    iteration: int = 0
    frozen_at: int | None = None
    elapsed: float = 0.0
    density_losses: list[float] = field(default_factory=list)  # the last two windows, for freezing
    density_steps: int = 0
    plateau_best: float = math.inf
    plateau_since: int = 0
    lr_scale: float = 1.0
    history: dict[str, list[float]] = field(default_factory=lambda: {key: [] for key in HISTORY_KEYS})


def state_from_json(data, iterations: int) -> TrainingState:
    """The loop state a checkpoint holds, checked field by field.

    Args:
        data: the ``state`` object of the checkpoint's description.
        iterations: the run's budget (no counter may pass it).

    Raises:
        DescriptionError: a missing, extra or mistyped field, or a value no run reaches.
    """
    data = require_dict(data, "state")
    names = {f.name for f in fields(TrainingState)}
    if set(data) != names:
        odd = [f"missing {n}" for n in sorted(names - set(data))] + [f"unknown {n}" for n in sorted(set(data) - names)]
        raise DescriptionError(f"state fields: {', '.join(odd[:3])}")
    iteration = require_int(data["iteration"], "state.iteration", 0, iterations)
    frozen_at = data["frozen_at"]
    if frozen_at is not None:
        frozen_at = require_int(frozen_at, "state.frozen_at", 0, iterations)
    losses = _numbers(data["density_losses"], "state.density_losses")
    history = require_dict(data["history"], "state.history")
    if set(history) != set(HISTORY_KEYS):
        raise DescriptionError(f"state.history has keys {sorted(history)}, not {sorted(HISTORY_KEYS)}")
    series = {key: _numbers(history[key], f"state.history.{key}") for key in HISTORY_KEYS}
    if len({len(values) for values in series.values()}) != 1:
        raise DescriptionError("state.history series differ in length")
    lr_scale = require_number(data["lr_scale"], "state.lr_scale")
    if not 0 < lr_scale <= 1:
        raise DescriptionError(f"state.lr_scale = {lr_scale} is out of range")
    elapsed = require_number(data["elapsed"], "state.elapsed")
    if elapsed < 0:
        raise DescriptionError(f"state.elapsed = {elapsed} is negative")
    plateau_best = require_number(data["plateau_best"], "state.plateau_best", finite=False)
    if plateau_best != plateau_best:
        raise DescriptionError("state.plateau_best is NaN")
    return TrainingState(
        iteration=iteration,
        frozen_at=frozen_at,
        elapsed=elapsed,
        density_losses=losses,
        density_steps=require_int(data["density_steps"], "state.density_steps", 0, iterations),
        plateau_best=plateau_best,
        plateau_since=require_int(data["plateau_since"], "state.plateau_since", 0, iterations),
        lr_scale=lr_scale,
        history=series,
    )


def check_tensors(tensors: dict[str, torch.Tensor], expected: dict[str, tuple[tuple[int, ...], torch.dtype]]) -> None:
    """Check that a checkpoint holds exactly the expected tensors, each of its shape and dtype.

    Raises:
        DescriptionError: a tensor missing, extra, or of another shape or dtype.
    """
    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    if missing or extra:
        names = [f"missing {name}" for name in missing[:3]] + [f"unexpected {name}" for name in extra[:3]]
        raise DescriptionError(", ".join(names))
    for name, (shape, dtype) in expected.items():
        tensor = tensors[name]
        if tuple(tensor.shape) != tuple(shape) or tensor.dtype != dtype:
            raise DescriptionError(
                f"{name} is {tensor.dtype} {list(tensor.shape)}, the run needs {dtype} {list(shape)}"
            )


def optimizer_layout(name: str, optimizer: torch.optim.Optimizer, with_state: bool
                     ) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """The tensors an Adam optimizer's state takes in a checkpoint (none before its first step).

    Args:
        name: the optimiser's name in the checkpoint (``network``, ``placement``).
        optimizer: the run's optimiser (its parameters give the shapes).
        with_state: whether it has stepped (then every parameter has its moments and step count).
    """
    if not with_state:
        return {}
    layout = {}
    parameters = [p for group in optimizer.param_groups for p in group["params"]]
    for index, parameter in enumerate(parameters):
        for key in ADAM_STATE:  # the moments have the parameter's shape; the step count is a scalar
            shape = () if key == "step" else tuple(parameter.shape)
            layout[f"optim.{name}.{index}.{key}"] = (shape, torch.float32 if key == "step" else parameter.dtype)
    return layout


def _numbers(value, name: str) -> list[float]:
    """A list of numbers, kept as stored (iterations stay ints, so a resumed history reads as a fresh one)."""
    if not isinstance(value, list):
        raise DescriptionError(f"{name} is not a list")
    for v in value:
        require_number(v, name, finite=False)
    return value
