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

SPERR (wavelets and SPECK coding) and TTHRESH (Tucker decomposition), the strongest classical coders at high
ratios, come through their ``numcodecs-wasm`` codecs. SPERR is measured in two modes: ``sperr``, a fixed rate in
bits per value (the mode a ratio is matched in: about ``32 / rate`` against float32), and ``sperr-pwe``, its
point-wise error mode with the absolute bound ``bound * range``, the error-bounded comparison. TTHRESH
(``tthresh``) targets a PSNR in dB; it bounds no single error.

Every compressor also names the range its setting may take for :func:`match_ratio`, which searches that range
for the setting whose compressed size gives an asked ratio.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import sys
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
    the value range; ``"precision"``, bit planes kept per block (no error bound); ``"rate"``, bits per value
    (no error bound); ``"psnr"``, a target PSNR in dB (no error bound).
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

    def search_range(self, volume: np.ndarray) -> "SettingRange":
        """The settings :func:`match_ratio` may try on ``volume``: value-range-relative bounds by default."""
        return SettingRange(low=1e-7, high=0.9)


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


    def search_range(self, volume: np.ndarray) -> "SettingRange":
        return SettingRange(low=1, high=32, log=False, integer=True)


class WasmCodecCompressor(Compressor):
    """A codec of the ``numcodecs-wasm`` family: ``_codec(volume, setting)`` builds it; its stream names its
    own shape and settings, so any instance of the codec decodes it."""

    def _module(self):
        import importlib

        return importlib.import_module(self.package.replace("-", "_"))

    def _codec(self, volume: np.ndarray, setting: float):
        raise NotImplementedError

    def _decoder(self):
        raise NotImplementedError

    def compress(self, volume: np.ndarray, setting: float) -> Compressed:
        volume = np.ascontiguousarray(volume, dtype=np.float32)
        codec = self._codec(volume, setting)
        with _quiet_stdout(), _codec_errors(f"{self.name} {self.setting} {setting:g}: its encoder"):
            stream = codec.encode(volume)  # TTHRESH prints its ratio on every call
        return Compressed(np.asarray(stream).tobytes(), tuple(volume.shape))

    def decompress(self, compressed: Compressed) -> np.ndarray:
        with _quiet_stdout(), _codec_errors(f"{self.name}: its decoder"):
            values = self._decoder().decode(np.frombuffer(compressed.data, dtype=np.uint8))
        return np.asarray(values, dtype=np.float32).reshape(compressed.shape)


class SPERRCompressor(WasmCodecCompressor):
    """SPERR (wavelets + SPECK) through ``numcodecs-wasm-sperr`` at a fixed rate: ``setting`` bits per value."""

    name = "sperr"
    package = "numcodecs-wasm-sperr"
    setting = "rate"

    def _codec(self, volume: np.ndarray, bits_per_value: float):
        if not 0 < bits_per_value <= 64:
            raise ApmgsrnError(f"sperr rate {bits_per_value!r}: must be bits per value in (0, 64]")
        if bits_per_value * volume.size < MIN_SPERR_BITS:
            raise ApmgsrnError(f"sperr rate {bits_per_value!r}: under {MIN_SPERR_BITS} bits for the whole "
                               f"{volume.size}-value volume")
        return self._module().Sperr(mode="bpp", bpp=float(bits_per_value))

    def _decoder(self):
        return self._module().Sperr(mode="bpp", bpp=1.0)

    def search_range(self, volume: np.ndarray) -> "SettingRange":
        return SettingRange(low=max(1e-4, MIN_SPERR_BITS / max(volume.size, 1)), high=32.0)


class SPERRBoundCompressor(SPERRCompressor):
    """SPERR in point-wise error mode: every error at most ``bound * range``."""

    name = "sperr-pwe"
    setting = "bound"

    def _codec(self, volume: np.ndarray, relative_bound: float):
        if not 0 < relative_bound < 1:
            raise ApmgsrnError(f"sperr-pwe bound {relative_bound!r}: must be a share of the value range in (0, 1)")
        value_range = float(volume.max() - volume.min()) if volume.size else 0.0
        # SPERR takes a positive absolute bound; a constant volume is coded exactly at any bound.
        bound = float(relative_bound) * value_range
        return self._module().Sperr(mode="pwe", pwe=bound if bound > 0 else 1.0)

    def search_range(self, volume: np.ndarray) -> "SettingRange":
        return Compressor.search_range(self, volume)


class TTHRESHCompressor(WasmCodecCompressor):
    """TTHRESH (Tucker decomposition) through ``numcodecs-wasm-tthresh``: ``setting`` is the target PSNR, dB."""

    name = "tthresh"
    package = "numcodecs-wasm-tthresh"
    setting = "psnr"

    def _codec(self, volume: np.ndarray, psnr: float):
        if not 0 < psnr <= MAX_PSNR:
            raise ApmgsrnError(f"tthresh PSNR {psnr!r}: must be in (0, {MAX_PSNR:g}] dB")
        return self._module().Tthresh(eb_mode="psnr", eb_psnr=float(psnr))

    def _decoder(self):
        return self._module().Tthresh(eb_mode="psnr", eb_psnr=40.0)

    def search_range(self, volume: np.ndarray) -> "SettingRange":
        return SettingRange(low=10.0, high=140.0, log=False)


#: Fewest bits SPERR's fixed-rate mode is given for a whole volume: below about one bit it ignores the budget
#: and writes more than the raw values.
MIN_SPERR_BITS = 64
#: Highest PSNR target, dB (float32 rounding is about 150 dB below the range).
MAX_PSNR = 200.0


class CodecFailed(ApmgsrnError):
    """A compressor's native code failed on a volume (TTHRESH's decoder does on some of its own streams)."""


@contextlib.contextmanager
def _codec_errors(what: str):
    """Turn the plain ``Exception`` a WebAssembly codec raises into :class:`CodecFailed` naming ``what``."""
    try:
        yield
    except ApmgsrnError:
        raise
    except Exception as error:  # the codecs raise bare Exception from their runtime
        raise CodecFailed(f"{what} failed: {str(error).splitlines()[0] if str(error) else type(error).__name__}") \
            from error


@contextlib.contextmanager
def _quiet_stdout():
    """Send what native code writes to file descriptor 1 to /dev/null meanwhile."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no descriptor 1 to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


COMPRESSORS: dict[str, type[Compressor]] = dict(zip(COMPRESSOR_NAMES, (
    SZ3Compressor, ZFPCompressor, ZFPPrecisionCompressor, SPERRCompressor, SPERRBoundCompressor, TTHRESHCompressor)))


def get_compressor(name: str) -> Compressor:
    """The compressor called ``name``.

    Raises:
        ApmgsrnError: unknown name.
    """
    if name not in COMPRESSORS:
        raise ApmgsrnError(f"unknown compressor {name!r}; choose from {', '.join(COMPRESSORS)}")
    return COMPRESSORS[name]()


@dataclass(frozen=True)
class SettingRange:
    """Where :func:`match_ratio` looks for a compressor's setting.

    Attributes:
        low, high: the settings tried first (both ends of the search; either may give the higher ratio).
        log: search in log(setting) (bounds and rates span decades), else linearly (dB).
        integer: only whole settings (bit planes).
    """

    low: float
    high: float
    log: bool = True
    integer: bool = False


@dataclass(frozen=True)
class RatioMatch:
    """The setting found for an asked ratio, its stream and the ratio it gives."""

    setting: float
    compressed: Compressed
    ratio: float
    trials: int


class RatioNotReached(ApmgsrnError):
    """No setting of a compressor gives the asked ratio within the tolerance."""


#: Relative distance from the asked ratio within which :func:`match_ratio` stops: a small fraction of a dB on
#: any rate-distortion curve.
RATIO_TOLERANCE = 0.01
#: How far the best setting found may land when none lands within the tolerance: the 5 % that ``--ratio``
#: promises for the networks. SZ3's ratio is not monotone in its bound (it moves by a few per cent between
#: nearby bounds) and ZFP's moves in steps, so an exact match may not exist.
RATIO_ACCEPT = 0.05
#: Compressions :func:`match_ratio` tries at most (its first grid included).
MAX_TRIALS = 40
#: Settings :func:`match_ratio` tries first, evenly over the compressor's range, ends included.
GRID_POINTS = 5


def match_ratio(compressor: Compressor, volume: np.ndarray, ratio: float, data_bytes: int,
                tolerance: float = RATIO_TOLERANCE, accept: float = RATIO_ACCEPT) -> RatioMatch:
    """The setting of ``compressor`` whose stream gives ``data_bytes / len(stream)`` within ``tolerance``
    (relative) of ``ratio``, or, when none is found, the nearest setting tried if it lands within ``accept``.

    A bracketing search over the compressor's :meth:`~Compressor.search_range`: :data:`GRID_POINTS` settings
    evenly spread over it first (ends included: a compressor's ratio need not be monotone in its setting), the
    neighbouring pair whose ratios straddle the asked one as the bracket, then a point interpolated in
    log(ratio) between the bracket's settings (kept inside its middle 80 % so that it always shrinks), until
    one lands within the tolerance, the bracket cannot shrink any more, or :data:`MAX_TRIALS` compressions
    were made.

    Raises:
        RatioNotReached: the ratio lies outside what the range's ends give, or no setting tried lands within
            ``accept`` (an integer setting between two whole values, or a compressor whose ratio jumps).
    """
    accept = max(accept, tolerance)
    span = compressor.search_range(volume)
    trials = 0
    best: RatioMatch | None = None

    def attempt(setting: float) -> float:
        nonlocal trials, best
        trials += 1
        compressed = compressor.compress(volume, setting)
        got = data_bytes / max(len(compressed.data), 1)
        if best is None or abs(math.log(got / ratio)) < abs(math.log(best.ratio / ratio)):
            best = RatioMatch(setting, compressed, got, trials)
        return got

    def within(got: float) -> bool:
        return abs(got / ratio - 1) <= tolerance

    def to_setting(x: float) -> float:
        value = math.exp(x) if span.log else x
        return float(round(value)) if span.integer else value

    low, high = (math.log(v) if span.log else v for v in (span.low, span.high))
    grid = [low + (high - low) * i / (GRID_POINTS - 1) for i in range(GRID_POINTS)]
    if span.integer:
        grid = sorted({float(round(x)) for x in grid})
    ratios = [attempt(to_setting(x)) for x in grid]
    if not (min(ratios) * (1 - accept) <= ratio <= max(ratios) * (1 + accept)):
        raise RatioNotReached(f"{compressor.name}: {ratio:,.4g}:1 is out of reach; its settings give "
                              f"{min(ratios):,.4g}:1 to {max(ratios):,.4g}:1 on this volume")
    straddling = [i for i in range(len(grid) - 1) if min(ratios[i:i + 2]) <= ratio <= max(ratios[i:i + 2])]
    if not straddling:  # just beyond the extremes, within ``accept``: the nearest grid point is the answer
        straddling, trials_left = [0], 0
    else:
        trials_left = MAX_TRIALS
    i = min(straddling, key=lambda j: sum(abs(math.log(r / ratio)) for r in ratios[j:j + 2]))
    # ``a`` is the bracket's end with the lower ratio, ``b`` the one with the higher.
    (xa, ra), (xb, rb) = sorted(zip(grid[i:i + 2], ratios[i:i + 2]), key=lambda pair: pair[1])
    while not within(best.ratio) and trials < trials_left:
        if to_setting(xa) == to_setting(xb) or (span.integer and abs(to_setting(xb) - to_setting(xa)) <= 1):
            break
        share = math.log(ratio / ra) / math.log(rb / ra) if rb > ra else 0.5
        x = xa + (xb - xa) * min(max(share, 0.1), 0.9)
        if span.integer:
            x = float(round(x))
            if x in (xa, xb):
                x = xa + math.copysign(1.0, xb - xa)
        got = attempt(to_setting(x))
        if got < ratio:
            xa, ra = x, got
        else:
            xb, rb = x, got
    if abs(best.ratio / ratio - 1) > accept:
        raise RatioNotReached(f"{compressor.name}: no setting gives {ratio:,.4g}:1 within {accept * 100:g} %; "
                              f"the nearest, {best.setting:g}, gives {best.ratio:,.4g}:1")
    return dataclasses.replace(best, trials=trials)
