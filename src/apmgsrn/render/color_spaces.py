"""Colour-space conversions and the interpolations ParaView offers between two colour-map nodes.

All functions work on numpy arrays of sRGB colours in ``[0, 1]`` with the channel as the last axis.
Lab is CIE L*a*b* with the D65 white point (what VTK uses); "Diverging" is Moreland's Msh interpolation
("Diverging Color Maps for Scientific Visualization", 2009), the colour space of ParaView's default
"Cool to Warm" map.
"""

from __future__ import annotations

import numpy as np

# sRGB primaries to CIE XYZ, D65 white (IEC 61966-2-1).
_RGB_TO_XYZ = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
_XYZ_TO_RGB = np.linalg.inv(_RGB_TO_XYZ)
_WHITE_D65 = np.array([0.95047, 1.0, 1.08883])
_LAB_EPSILON = 216.0 / 24389.0  # (6/29)^3: where the cube root gives way to the linear segment
_LAB_KAPPA = 24389.0 / 27.0

SUPPORTED_COLOR_SPACES = ("RGB", "Lab", "Diverging", "HSV", "Step")


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """Undo the sRGB transfer curve. Args: rgb ``[..., 3]`` in [0, 1]. Returns: linear ``[..., 3]``."""
    rgb = np.asarray(rgb, dtype=np.float64)
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Apply the sRGB transfer curve. Args: linear ``[..., 3]``. Returns: sRGB ``[..., 3]`` clipped to [0, 1]."""
    linear = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1.0 / 2.4) - 0.055)


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB to CIE Lab (D65).

    Args:
        rgb: ``[..., 3]`` sRGB in [0, 1].

    Returns:
        ``[..., 3]`` (L, a, b), L in [0, 100].
    """
    xyz = srgb_to_linear(rgb) @ _RGB_TO_XYZ.T / _WHITE_D65
    f = np.where(xyz > _LAB_EPSILON, np.cbrt(xyz), (_LAB_KAPPA * xyz + 16.0) / 116.0)
    lightness = 116.0 * f[..., 1] - 16.0
    a = 500.0 * (f[..., 0] - f[..., 1])
    b = 200.0 * (f[..., 1] - f[..., 2])
    return np.stack([lightness, a, b], axis=-1)


def lab_to_rgb(lab: np.ndarray) -> np.ndarray:
    """CIE Lab (D65) to sRGB, clipped to the gamut.

    Args:
        lab: ``[..., 3]`` (L, a, b).

    Returns:
        ``[..., 3]`` sRGB in [0, 1].
    """
    lab = np.asarray(lab, dtype=np.float64)
    fy = (lab[..., 0] + 16.0) / 116.0
    fx = fy + lab[..., 1] / 500.0
    fz = fy - lab[..., 2] / 200.0
    f = np.stack([fx, fy, fz], axis=-1)
    xyz = np.where(f**3 > _LAB_EPSILON, f**3, (116.0 * f - 16.0) / _LAB_KAPPA) * _WHITE_D65
    return linear_to_srgb(xyz @ _XYZ_TO_RGB.T)


def rgb_to_msh(rgb: np.ndarray) -> np.ndarray:
    """sRGB to Moreland's polar Lab form (M, s, h): magnitude, saturation angle, hue angle."""
    lab = rgb_to_lab(rgb)
    magnitude = np.linalg.norm(lab, axis=-1)
    saturation = np.arccos(np.clip(lab[..., 0] / np.maximum(magnitude, 1e-12), -1.0, 1.0))
    hue = np.arctan2(lab[..., 2], lab[..., 1])
    return np.stack([magnitude, saturation, hue], axis=-1)


def msh_to_rgb(msh: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgb_to_msh`."""
    msh = np.asarray(msh, dtype=np.float64)
    m, s, h = msh[..., 0], msh[..., 1], msh[..., 2]
    lab = np.stack([m * np.cos(s), m * np.sin(s) * np.cos(h), m * np.sin(s) * np.sin(h)], axis=-1)
    return lab_to_rgb(lab)


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """sRGB to HSV, hue in [0, 1)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    high = rgb.max(axis=-1)
    low = rgb.min(axis=-1)
    chroma = high - low
    safe = np.where(chroma > 0, chroma, 1.0)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    hue = np.where(
        high == r, ((g - b) / safe) % 6.0, np.where(high == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0)
    )
    hue = np.where(chroma > 0, hue / 6.0, 0.0)
    saturation = np.where(high > 0, chroma / np.where(high > 0, high, 1.0), 0.0)
    return np.stack([hue, saturation, high], axis=-1)


def hsv_to_rgb(hsv: np.ndarray) -> np.ndarray:
    """HSV (hue in [0, 1)) to sRGB."""
    hsv = np.asarray(hsv, dtype=np.float64)
    h6 = (hsv[..., 0] % 1.0) * 6.0
    s, v = hsv[..., 1], hsv[..., 2]
    # Standard piecewise form: each channel is v minus a clipped triangle wave of the hue.
    k = np.stack([(5.0 + h6) % 6.0, (3.0 + h6) % 6.0, (1.0 + h6) % 6.0], axis=-1)
    return v[..., None] - v[..., None] * s[..., None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _adjust_hue(msh: np.ndarray, unsaturated_magnitude: float) -> float:
    """Hue to give an unsaturated end so the ramp towards the saturated one keeps a constant hue spin."""
    m, s, h = msh
    if m >= unsaturated_magnitude:
        return float(h)
    spin = s * np.sqrt(unsaturated_magnitude**2 - m**2) / (m * np.sin(s))
    return float(h + spin) if h > -np.pi / 3.0 else float(h - spin)


def interpolate_diverging(rgb0: np.ndarray, rgb1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Moreland's diverging interpolation between two colours.

    Args:
        rgb0, rgb1: ``[3]`` end colours.
        t: ``[N]`` positions in [0, 1].

    Returns:
        ``[N, 3]`` sRGB colours.
    """
    t = np.asarray(t, dtype=np.float64)
    msh0 = rgb_to_msh(np.asarray(rgb0, dtype=np.float64))
    msh1 = rgb_to_msh(np.asarray(rgb1, dtype=np.float64))
    out = np.empty(t.shape + (3,))
    hue_gap = abs(msh0[2] - msh1[2])
    hue_gap = min(hue_gap, 2 * np.pi - hue_gap)
    if msh0[1] > 0.05 and msh1[1] > 0.05 and hue_gap > np.pi / 3.0:
        # Two distinct saturated hues: pass through an unsaturated (white-ish) centre.
        centre = np.array([max(msh0[0], msh1[0], 88.0), 0.0, 0.0])
        low = t < 0.5
        out[low] = _interpolate_msh(msh0, centre, 2.0 * t[low])
        out[~low] = _interpolate_msh(centre, msh1, 2.0 * t[~low] - 1.0)
        return out
    return _interpolate_msh(msh0, msh1, t)


def _interpolate_msh(msh0: np.ndarray, msh1: np.ndarray, t: np.ndarray) -> np.ndarray:
    msh0 = msh0.copy()
    msh1 = msh1.copy()
    if msh0[1] < 0.05 and msh1[1] > 0.05:
        msh0[2] = _adjust_hue(msh1, msh0[0])
    elif msh1[1] < 0.05 and msh0[1] > 0.05:
        msh1[2] = _adjust_hue(msh0, msh1[0])
    msh = (1.0 - t)[:, None] * msh0 + t[:, None] * msh1  # [N, 3]
    return msh_to_rgb(msh)


def interpolate_colors(rgb0: np.ndarray, rgb1: np.ndarray, t: np.ndarray, space: str) -> np.ndarray:
    """Interpolate between two colour-map nodes the way ParaView's colour spaces do.

    Args:
        rgb0, rgb1: ``[3]`` sRGB end colours.
        t: ``[N]`` positions in [0, 1].
        space: one of ``SUPPORTED_COLOR_SPACES``.

    Returns:
        ``[N, 3]`` sRGB in [0, 1].
    """
    rgb0 = np.asarray(rgb0, dtype=np.float64)
    rgb1 = np.asarray(rgb1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if space == "RGB":
        return (1.0 - t)[:, None] * rgb0 + t[:, None] * rgb1
    if space == "Step":
        # ParaView's "Step" holds each node's colour up to the next node.
        return np.where((t < 1.0)[:, None], rgb0, rgb1)
    if space == "Lab":
        lab = (1.0 - t)[:, None] * rgb_to_lab(rgb0) + t[:, None] * rgb_to_lab(rgb1)
        return lab_to_rgb(lab)
    if space == "HSV":
        hsv0, hsv1 = rgb_to_hsv(rgb0), rgb_to_hsv(rgb1)
        # Go round the hue circle the short way, as VTK does by default.
        dh = hsv1[0] - hsv0[0]
        if dh > 0.5:
            dh -= 1.0
        elif dh < -0.5:
            dh += 1.0
        hue = (hsv0[0] + t * dh) % 1.0
        rest = (1.0 - t)[:, None] * hsv0[1:] + t[:, None] * hsv1[1:]
        return hsv_to_rgb(np.concatenate([hue[:, None], rest], axis=1))
    if space == "Diverging":
        return interpolate_diverging(rgb0, rgb1, t)
    raise ValueError(f"unknown colour space {space!r}")
