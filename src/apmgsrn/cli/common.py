"""Arguments and helpers shared by several sub-commands."""

from __future__ import annotations

import argparse

from apmgsrn.choices import DECODER_PRECISIONS
from apmgsrn.errors import ApmgsrnError
from apmgsrn.options import INPUT, add_option_arguments, read_options


def add_data_arguments(parser: argparse.ArgumentParser) -> None:
    """Options that say how to read a volume file (:data:`apmgsrn.options.INPUT`)."""
    add_option_arguments(parser, (INPUT,))


def volume_options(args: argparse.Namespace, allow_series: bool = False) -> dict:
    """Keyword arguments of :func:`apmgsrn.data.open_volume` (or, with ``allow_series``, of a series' opener) from
    the data options of ``args`` (:func:`apmgsrn.options.read_options`)."""
    return read_options(args, allow_series)


def open_data(args: argparse.Namespace, path: str):
    """Open the volume at ``path`` with the data options of ``args``."""
    from apmgsrn.data import open_volume

    return open_volume(path, **volume_options(args))


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """``--device``."""
    parser.add_argument("--device", default="auto", help="auto (default), cpu, cuda or cuda:I")


def add_precision_argument(parser: argparse.ArgumentParser, default: str, purpose: str) -> None:
    """``--precision``: the arithmetic of inference (``apmgsrn.load(precision=...)``)."""
    parser.add_argument(
        "--precision", choices=DECODER_PRECISIONS, default=default,
        help=f"arithmetic of the network (default {default}{purpose}): float32; bfloat16 hidden layers (faster "
             "than float32 matrix products where the CPU multiplies bfloat16 natively, emulated and slow elsewhere, "
             "slower than the fused float32 kernels of APMGSRN and the hybrid everywhere measured; values move by "
             "up to about 0.5 %% of the range, and a --max-error bound is not kept); auto = bfloat16 on such CPUs "
             "for a model without a fused float32 kernel, float32 elsewhere")


def format_bytes(count: float) -> str:
    """``1536`` -> ``"1.5 KB"``."""
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(count) < 1024 or unit == "TB":
            return f"{count:.1f} {unit}" if unit != "B" else f"{int(count)} B"
        count /= 1024
    return f"{count} B"


def percent_of_range(error: float, low: float, high: float) -> str:
    """An error as a share of a value range, e.g. ``"0.41 % of the value range"``."""
    span = high - low
    return f"{100 * error / span:.2g} % of the value range" if span > 0 else "constant data"


def compression_figures(voxels: int, dtype: str | None, itemsize: int | None, model_bytes: int) -> dict:
    """Compression ratios of docs/method.md §8: against the data as stored (its own dtype: a uint8 volume is 1
    byte a voxel) and against float32.

    Args:
        voxels: voxels of the volume.
        dtype: its stored dtype (None: unknown, e.g. a model file written before the dtype was recorded).
        itemsize: bytes a stored voxel takes (None with an unknown dtype).
        model_bytes: size of the model file or folder.

    Returns:
        ``data_dtype``, ``data_bytes``, ``float32_bytes``, ``compression_ratio`` (stored bytes / model bytes;
        None when the dtype is unknown) and ``compression_ratio_float32``.
    """
    data_bytes = voxels * itemsize if itemsize else None
    return {
        "data_dtype": dtype,
        "data_bytes": data_bytes,
        "float32_bytes": voxels * 4,
        "compression_ratio": data_bytes / model_bytes if data_bytes and model_bytes else None,
        "compression_ratio_float32": voxels * 4 / model_bytes if model_bytes else None,
    }


def compression_text(figures: dict) -> str:
    """``"1.7x against the stored uint8 data, 6.6x against float32"`` (one figure when they agree)."""
    float32 = f"{figures['compression_ratio_float32']:.1f}x against float32"
    if figures["compression_ratio"] is None:
        return f"{float32} (stored data type not recorded)"
    stored = f"{figures['compression_ratio']:.1f}x against the stored {figures['data_dtype']} data"
    return stored if figures["data_bytes"] == figures["float32_bytes"] else f"{stored}, {float32}"
