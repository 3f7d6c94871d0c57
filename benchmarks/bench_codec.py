"""The entropy coder of packed files against zstandard: LZMA (raw, as io/codec.py codes) and numcodecs' Zstd at
level 22 on the same bytes (each tensor quantised to B bits, its best predictor, zigzag byte planes).

Prints, per model and bit width, the total coded bytes of every tensor's integers with each coder. Sizes
only; nothing is timed.

Usage::

    python benchmarks/bench_codec.py MODEL [MODEL ...] [--bits 6,8,10]
"""

from __future__ import annotations

import argparse
import sys

import numcodecs

import apmgsrn
from apmgsrn.io import codec
from apmgsrn.io.quantization import group_size, quantize, steps_for_bits


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--bits", default="6,8,10")
    args = parser.parse_args()
    zstd = numcodecs.Zstd(level=22)
    print("| model | bits | LZMA bytes | zstd-22 bytes | LZMA / zstd |\n|---|---:|---:|---:|---:|")
    for path in args.models:
        state = apmgsrn.load(path).field.state_dict()
        for bits in (int(b) for b in args.bits.split(",")):
            lzma_bytes = zstd_bytes = 0
            for tensor in state.values():
                values = tensor.numpy()
                size = group_size(values.shape)
                levels = quantize(values, steps_for_bits(values, size, bits), size).levels
                coded, width, predictor = codec.best_encoding(levels, values.shape)
                lzma_bytes += len(coded)
                zstd_bytes += len(zstd.encode(codec.to_bytes(codec.predict(levels, values.shape, predictor), width)))
            print(f"| {path.split('/')[-1]} | {bits} | {lzma_bytes:,} | {zstd_bytes:,} | {lzma_bytes / zstd_bytes:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
