"""Triton, where it is installed: the one import the Triton backends share, and whether they can run.

Triton is optional (extra ``gpu``); without it ``triton`` and ``tl`` are None and the backends report
themselves unavailable. Importing this compiles nothing and does not touch CUDA.
"""

from __future__ import annotations

import torch

try:
    import triton
    import triton.language as tl

    IMPORT_ERROR: str | None = None
except ImportError as err:  # pragma: no cover - depends on the environment
    triton = None
    tl = None
    IMPORT_ERROR = f"triton is not installed ({err})"


def is_available() -> bool:
    """True when Triton is importable and a CUDA device is present."""
    return triton is not None and torch.cuda.is_available()


def load_error() -> str | None:
    """Why :func:`is_available` is False (``None`` when it is True)."""
    if triton is None:
        return IMPORT_ERROR
    if not torch.cuda.is_available():
        return "no CUDA device"
    return None
