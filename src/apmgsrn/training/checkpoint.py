"""Training checkpoints (``MODEL.ckpt``): the whole state of an unfinished run, so it resumes exactly.

A checkpoint is a :mod:`apmgsrn.io.container` file of kind ``training-state``: the field's tensors, the
optimisers' moments and the random generator's state, plus a JSON description (run fingerprint, config,
loop state, optimiser parameter groups). Written atomically: a kill at any moment leaves the previous one.
"""

from __future__ import annotations

from pathlib import Path

CHECKPOINT_KIND = "training-state"


def checkpoint_path_for(model_path: str | Path) -> Path:
    """The training checkpoint beside a model file (``MODEL.ckpt``)."""
    return Path(str(model_path) + ".ckpt")
