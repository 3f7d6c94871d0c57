"""Device choice shared by every command: ``auto``, ``cpu``, ``cuda`` or ``cuda:I``."""

from __future__ import annotations

import torch

from apmgsrn.errors import ApmgsrnError


def resolve_device(name: str = "auto") -> torch.device:
    """Turn a user's device name into a torch device, checking that it exists.

    Raises:
        ApmgsrnError: CUDA was asked for and is not available, or the name is unknown.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ApmgsrnError(f"unknown device {name!r}; use auto, cpu, cuda or cuda:I") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ApmgsrnError(f"device {name!r} asked for, but no CUDA GPU is available; pass device=cpu",
                               arguments=("device",))
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ApmgsrnError(
                f"device {name!r} asked for, but only {torch.cuda.device_count()} CUDA GPU(s) exist"
            )
    elif device.type != "cpu":
        raise ApmgsrnError(f"unsupported device {name!r}; use auto, cpu, cuda or cuda:I")
    return device


def keep_large_allocations_cached() -> None:
    """Stop glibc from returning large blocks to the OS after every free.

    PyTorch's CPU allocator is plain malloc: each multi-megabyte activation would otherwise be a fresh
    mmap whose pages fault in on first touch, which costs more than the arithmetic of a small MLP.
    Harmless where glibc is absent.
    """
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 1 << 30)
        libc.mallopt(m_trim_threshold, 1 << 31)
    except (OSError, AttributeError):
        pass
