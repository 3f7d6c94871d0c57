"""Device choice shared by every command: ``auto``, ``cpu``, ``cuda`` or ``cuda:I``."""

from __future__ import annotations

import functools

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


@functools.cache
def cpu_has_native_bfloat16() -> bool:
    """Whether this CPU has bfloat16 dot-product instructions (elsewhere oneDNN emulates them, slowly)."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            flags = next((line.split() for line in cpuinfo if line.startswith("flags")), [])
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def inference_dtype(precision: str, device: torch.device | str) -> torch.dtype | None:
    """The decoder's hidden-layer dtype for inference at ``precision`` (None: float32 throughout).

    Args:
        precision: ``"float32"``, ``"bfloat16"``, or ``"auto"``: bfloat16 on CPUs that multiply it
            natively (AVX512-BF16 or AMX), float32 elsewhere (emulated bfloat16 is slower than the fused
            float32 kernel, and GPUs are not measured yet).
        device: where the model runs.

    Raises:
        InvalidArgument: an unknown precision.
    """
    from apmgsrn.arguments import check_choice
    from apmgsrn.choices import DECODER_PRECISIONS

    check_choice("precision", precision, DECODER_PRECISIONS)
    if precision == "bfloat16":
        return torch.bfloat16
    if precision == "auto" and torch.device(device).type == "cpu" and cpu_has_native_bfloat16():
        return torch.bfloat16
    return None
