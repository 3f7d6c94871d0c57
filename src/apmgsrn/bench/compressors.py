"""Lossy compressors to compare the networks with: SZ3 (``pysz``) and ZFP (``zfpy``).

Both are optional (``pip install 'apmgsrn[baselines]'``); each is imported only when used. Error bounds
are relative to the volume's value range (``max - min``), the form both compressors can honour: SZ3's
``REL`` mode and ZFP's fixed-accuracy mode with tolerance ``bound * range``. Either guarantees
``max |x - x'| <= bound * range`` (ZFP's tolerance is a bound it meets with margin).

ZFP's fixed-accuracy mode keeps about eight bit planes more than the tolerance asks for, so on values of
few significant bits (Miranda's density, the channel's pressure) it is exact, or nearly, at any tolerance
and never passes about 30:1. Its fixed-precision mode (``zfp-precision``: a number of bit planes per block,
no error bound) reaches about 200:1 on any volume; measuring both is what ZFP can do at high ratios.
(The fixed-rate mode is left out: it gives about the same quality at these ratios, and cannot go further,
since below 9 bits a block, 0.14 bit a value or about 230:1, ``zfpy`` writes past its buffer and crashes.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from apmgsrn.choices import COMPRESSORS as COMPRESSOR_NAMES
from apmgsrn.errors import ApmgsrnError

INSTALL_HINT = "pip install 'apmgsrn[baselines]'"


@dataclass(frozen=True)
class Compressed:
    """A compressed volume: the byte stream and what decompression needs besides it."""

    data: bytes
    shape: tuple[int, ...]


class Compressor:
    """One lossy compressor; subclasses name their package and implement the two directions.

    ``setting`` says what the number each compression takes means: ``"bound"``, an error bound relative to
    the value range; ``"precision"``, bit planes kept per block (no error bound).
    """

    name = ""
    package = ""
    setting = "bound"

    def available(self) -> bool:
        """True when the compressor's package imports here."""
        try:
            self._module()
        except ImportError:
            return False
        return True

    def unavailable_reason(self) -> str:
        """Why :meth:`available` is False, with the fix."""
        return f"{self.name}: the {self.package!r} package is not installed; {INSTALL_HINT}"

    def _module(self):
        raise NotImplementedError

    def compress(self, volume: np.ndarray, setting: float) -> Compressed:
        """Compress a float32 ``[D, H, W]`` volume; with a ``"bound"`` setting every error is at most
        ``setting * range``."""
        raise NotImplementedError

    def decompress(self, compressed: Compressed) -> np.ndarray:
        """The float32 ``[D, H, W]`` volume back."""
        raise NotImplementedError


class SZ3Compressor(Compressor):
    """SZ3 (prediction + quantisation + entropy coding) through ``pysz``, value-range-relative bound."""

    name = "sz3"
    package = "pysz"

    def _module(self):
        import pysz

        return pysz

    def compress(self, volume: np.ndarray, relative_bound: float) -> Compressed:
        pysz = self._module()
        config = pysz.szConfig()
        config.errorBoundMode = pysz.szErrorBoundMode.REL
        config.relErrorBound = float(relative_bound)
        stream, _ratio = pysz.sz.compress(np.ascontiguousarray(volume, dtype=np.float32), config)
        return Compressed(stream.tobytes(), tuple(volume.shape))

    def decompress(self, compressed: Compressed) -> np.ndarray:
        pysz = self._module()
        stream = np.frombuffer(compressed.data, dtype=np.uint8)
        values, _config = pysz.sz.decompress(stream, np.float32, compressed.shape)
        return values


class ZFPCompressor(Compressor):
    """ZFP (block transform coding) through ``zfpy`` in fixed-accuracy mode."""

    name = "zfp"
    package = "zfpy"

    def _module(self):
        import zfpy

        return zfpy

    def compress(self, volume: np.ndarray, relative_bound: float) -> Compressed:
        zfpy = self._module()
        volume = np.ascontiguousarray(volume, dtype=np.float32)
        value_range = float(volume.max() - volume.min()) if volume.size else 0.0
        # ZFP's tolerance is absolute; a constant volume (range 0) is coded losslessly by tolerance 0.
        tolerance = float(relative_bound) * value_range
        return Compressed(zfpy.compress_numpy(volume, tolerance=tolerance), tuple(volume.shape))

    def decompress(self, compressed: Compressed) -> np.ndarray:
        zfpy = self._module()
        return zfpy.decompress_numpy(compressed.data)


class ZFPPrecisionCompressor(ZFPCompressor):
    """ZFP through ``zfpy`` in fixed-precision mode: ``setting`` bit planes per block (1-32), no error bound."""

    name = "zfp-precision"
    setting = "precision"

    def compress(self, volume: np.ndarray, setting: float) -> Compressed:
        zfpy = self._module()
        precision = int(setting)
        if not 1 <= precision <= 32 or precision != setting:
            raise ApmgsrnError(f"zfp precision {setting!r}: must be a whole number of bit planes, 1 to 32")
        volume = np.ascontiguousarray(volume, dtype=np.float32)
        return Compressed(zfpy.compress_numpy(volume, precision=precision), tuple(volume.shape))


COMPRESSORS: dict[str, type[Compressor]] = dict(
    zip(COMPRESSOR_NAMES, (SZ3Compressor, ZFPCompressor, ZFPPrecisionCompressor)))


def get_compressor(name: str) -> Compressor:
    """The compressor called ``name``.

    Raises:
        ApmgsrnError: unknown name.
    """
    if name not in COMPRESSORS:
        raise ApmgsrnError(f"unknown compressor {name!r}; choose from {', '.join(COMPRESSORS)}")
    return COMPRESSORS[name]()
