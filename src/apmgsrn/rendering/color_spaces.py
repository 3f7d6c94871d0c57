"""Colour-space conversions and the interpolations ParaView applies between two colour-map nodes.

ParaView colours through VTK's ``vtkColorTransferFunction``, so every formula and constant here is VTK's:
sRGB <-> XYZ with VTK's four-digit matrices (the two are not exact inverses), CIE Lab against VTK's white
``(0.9505, 1.0, 1.089)`` with its ``0.008856`` / ``7.787`` linear segment, an out-of-gamut colour scaled
down by its largest channel before negatives are cut to 0, and Moreland's "Diverging" (Msh) interpolation
("Diverging Color Maps for Scientific Visualization", 2009) with VTK's thresholds. Matching these
exactly matters: ParaView's "Viridis (matplotlib)" is 256 nodes in the Diverging space, and near its hue
seam (the sign of Lab's ``b``) a different white point picks the other branch of ``atan2``.

All functions take numpy arrays of sRGB colours in ``[0, 1]`` with the channel as the last axis; the
interpolations take per-sample end colours ``[N, 3]`` and positions ``[N]``.
"""

from __future__ import annotations

import numpy as np

# VTK's sRGB <-> XYZ matrices (D65, 2 degree observer), four digits as vtkMath has them.
_RGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
_XYZ_TO_RGB = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
_WHITE = np.array([0.9505, 1.0, 1.089])

# ParaView's colour-space names, in the order of its enumeration (a preset may give the number).
PARAVIEW_COLOR_SPACES = ("RGB", "HSV", "Lab", "Diverging", "Lab/CIEDE2000", "Step")
SUPPORTED_COLOR_SPACES = ("RGB", "HSV", "Lab", "Diverging", "Step")


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """Undo the sRGB transfer curve. Args: rgb ``[..., 3]`` in [0, 1]. Returns: linear ``[..., 3]``."""
    rgb = np.asarray(rgb, dtype=np.float64)
    return np.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Apply the sRGB transfer curve, unclipped. Args: linear ``[..., 3]``. Returns: sRGB ``[..., 3]``."""
    linear = np.asarray(linear, dtype=np.float64)
    curved = 1.055 * np.power(np.abs(linear), 1.0 / 2.4) - 0.055  # abs: only used where linear > 0
    return np.where(linear > 0.0031308, curved, 12.92 * linear)


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB to CIE Lab as VTK computes it.

    Args:
        rgb: ``[..., 3]`` sRGB in [0, 1].

    Returns:
        ``[..., 3]`` (L, a, b), L in [0, 100].
    """
    xyz = srgb_to_linear(rgb) @ _RGB_TO_XYZ.T / _WHITE
    # CIE: the cube root gives way to a line of slope 7.787 below 0.008856
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16.0 / 116.0)
    lightness = 116.0 * f[..., 1] - 16.0
    return np.stack([lightness, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], axis=-1)


def lab_to_rgb(lab: np.ndarray) -> np.ndarray:
    """CIE Lab to sRGB as VTK computes it, brought into the gamut the way VTK does.

    A colour with a channel above 1 is divided by its largest channel (keeping its hue), then negative
    channels are set to 0.

    Args:
        lab: ``[..., 3]`` (L, a, b).

    Returns:
        ``[..., 3]`` sRGB in [0, 1].
    """
    lab = np.asarray(lab, dtype=np.float64)
    fy = (lab[..., 0] + 16.0) / 116.0
    f = np.stack([lab[..., 1] / 500.0 + fy, fy, fy - lab[..., 2] / 200.0], axis=-1)
    cubed = f**3
    xyz = np.where(cubed > 0.008856, cubed, (f - 16.0 / 116.0) / 7.787) * _WHITE  # the inverse of rgb_to_lab's
    rgb = linear_to_srgb(xyz @ _XYZ_TO_RGB.T)
    largest = rgb.max(axis=-1, keepdims=True)
    rgb = np.where(largest > 1.0, rgb / np.where(largest > 1.0, largest, 1.0), rgb)
    return np.maximum(rgb, 0.0)


def rgb_to_msh(rgb: np.ndarray) -> np.ndarray:
    """sRGB to Moreland's polar Lab (M, s, h); s is 0 below M 0.001 and h is 0 below s 0.001, as in VTK."""
    lab = rgb_to_lab(rgb)
    magnitude = np.linalg.norm(lab, axis=-1)
    ratio = lab[..., 0] / np.where(magnitude > 0.001, magnitude, 1.0)
    saturation = np.where(magnitude > 0.001, np.arccos(np.clip(ratio, -1.0, 1.0)), 0.0)
    hue = np.where(saturation > 0.001, np.arctan2(lab[..., 2], lab[..., 1]), 0.0)
    return np.stack([magnitude, saturation, hue], axis=-1)


def msh_to_rgb(msh: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgb_to_msh` (through :func:`lab_to_rgb`)."""
    msh = np.asarray(msh, dtype=np.float64)
    m, s, h = msh[..., 0], msh[..., 1], msh[..., 2]
    lab = np.stack([m * np.cos(s), m * np.sin(s) * np.cos(h), m * np.sin(s) * np.sin(h)], axis=-1)
    return lab_to_rgb(lab)


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """sRGB to HSV, hue in [0, 1) (0 for greys), as VTK computes it."""
    rgb = np.asarray(rgb, dtype=np.float64)
    high = rgb.max(axis=-1)
    chroma = high - rgb.min(axis=-1)
    safe = np.where(chroma > 0, chroma, 1.0)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    # VTK's order: red first, then green, then blue when channels tie for the largest.
    hue = np.where(
        r == high,
        (g - b) / safe / 6.0,
        np.where(g == high, 1.0 / 3.0 + (b - r) / safe / 6.0, 2.0 / 3.0 + (r - g) / safe / 6.0),
    )
    hue = np.where(chroma > 0, np.where(hue < 0.0, hue + 1.0, hue), 0.0)
    saturation = np.where(high > 0, chroma / np.where(high > 0, high, 1.0), 0.0)
    return np.stack([hue, saturation, high], axis=-1)


def hsv_to_rgb(hsv: np.ndarray) -> np.ndarray:
    """HSV (hue in [0, 1], 1 the same as 0) to sRGB."""
    hsv = np.asarray(hsv, dtype=np.float64)
    h6 = (hsv[..., 0] % 1.0) * 6.0
    s, v = hsv[..., 1], hsv[..., 2]
    # Each channel is v minus a clipped triangle wave of the hue.
    k = np.stack([(5.0 + h6) % 6.0, (3.0 + h6) % 6.0, (1.0 + h6) % 6.0], axis=-1)
    return v[..., None] - v[..., None] * s[..., None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest angle between two hue angles (radians), in [0, pi]."""
    gap = np.abs(a - b) % (2.0 * np.pi)
    return np.where(gap > np.pi, 2.0 * np.pi - gap, gap)


def _spun_hue(saturated: np.ndarray, unsaturated_magnitude: np.ndarray) -> np.ndarray:
    """Hue for an unsaturated end so the ramp from the saturated end ``[N, 3]`` keeps a steady hue spin."""
    m, s, h = saturated[:, 0], saturated[:, 1], saturated[:, 2]
    gap = np.maximum(unsaturated_magnitude**2 - m**2, 0.0)
    spin = s * np.sqrt(gap) / np.where(m * np.sin(s) != 0, m * np.sin(s), 1.0)
    # VTK spins away from hue 0 except for purples; it holds the hue when the magnitudes are close.
    spun = np.where(h > -0.3 * np.pi, h + spin, h - spin)
    return np.where(m >= unsaturated_magnitude - 0.1, h, spun)


def interpolate_diverging(rgb0: np.ndarray, rgb1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Moreland's diverging interpolation as VTK does it.

    Two saturated ends whose hues differ by more than 0.33 pi get an unsaturated centre (magnitude at
    least 88) at ``t = 0.5``; an unsaturated end takes a hue spun from the saturated one; then M, s and h
    are interpolated linearly (the hue without wrapping, as VTK does).

    Args:
        rgb0, rgb1: ``[N, 3]`` end colours of each sample's segment.
        t: ``[N]`` positions in [0, 1].

    Returns:
        ``[N, 3]`` sRGB colours.
    """
    msh0 = rgb_to_msh(rgb0)  # [N, 3]
    msh1 = rgb_to_msh(rgb1)
    t = np.asarray(t, dtype=np.float64).copy()
    split = (msh0[:, 1] > 0.05) & (msh1[:, 1] > 0.05) & (_angle_between(msh0[:, 2], msh1[:, 2]) > 0.33 * np.pi)
    white = np.maximum(np.maximum(msh0[:, 0], msh1[:, 0]), 88.0)
    centre = np.stack([white, np.zeros_like(t), np.zeros_like(t)], axis=1)
    first_half = split & (t < 0.5)
    second_half = split & ~(t < 0.5)
    msh1 = np.where(first_half[:, None], centre, msh1)
    msh0 = np.where(second_half[:, None], centre, msh0)
    t = np.where(first_half, 2.0 * t, np.where(second_half, 2.0 * t - 1.0, t))
    grey0 = (msh0[:, 1] < 0.05) & (msh1[:, 1] > 0.05)
    grey1 = (msh1[:, 1] < 0.05) & (msh0[:, 1] > 0.05)
    msh0[:, 2] = np.where(grey0, _spun_hue(msh1, msh0[:, 0]), msh0[:, 2])
    msh1[:, 2] = np.where(grey1, _spun_hue(msh0, msh1[:, 0]), msh1[:, 2])
    return msh_to_rgb((1.0 - t)[:, None] * msh0 + t[:, None] * msh1)


def interpolate_hsv(rgb0: np.ndarray, rgb1: np.ndarray, t: np.ndarray, wrap: bool) -> np.ndarray:
    """Linear interpolation in HSV.

    Args:
        rgb0, rgb1: ``[N, 3]`` end colours.
        t: ``[N]`` positions in [0, 1].
        wrap: go round the hue circle the short way (VTK's ``HSVWrap``). ParaView applies presets with
            it off unless the preset says ``"HSVWrap": 1``, so "Blue to Red Rainbow" passes through green.

    Returns:
        ``[N, 3]`` sRGB colours.
    """
    hsv0, hsv1 = rgb_to_hsv(rgb0), rgb_to_hsv(rgb1)  # [N, 3]
    if wrap:  # move the higher hue down by a turn when the two are more than half a turn apart
        far = np.abs(hsv0[:, 0] - hsv1[:, 0]) > 0.5
        first_higher = hsv0[:, 0] > hsv1[:, 0]
        hsv0[:, 0] -= far & first_higher
        hsv1[:, 0] -= far & ~first_higher
    hsv = (1.0 - t)[:, None] * hsv0 + t[:, None] * hsv1
    hsv[:, 0] = np.where(hsv[:, 0] < 0.0, hsv[:, 0] + 1.0, hsv[:, 0])
    return hsv_to_rgb(hsv)


def interpolate_colors(
    rgb0: np.ndarray, rgb1: np.ndarray, t: np.ndarray, space: str, hsv_wrap: bool = False
) -> np.ndarray:
    """The colour a fraction ``t`` of the way between two colour-map nodes, in one of ParaView's spaces.

    Args:
        rgb0, rgb1: ``[N, 3]`` sRGB colours of each sample's lower and upper node.
        t: ``[N]`` positions in (0, 1].
        space: one of ``SUPPORTED_COLOR_SPACES``. ``Step`` is the upper node's colour (VTK's step mode).
        hsv_wrap: for ``HSV`` only, see :func:`interpolate_hsv`.

    Returns:
        ``[N, 3]`` sRGB in [0, 1].
    """
    rgb0 = np.asarray(rgb0, dtype=np.float64)
    rgb1 = np.asarray(rgb1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if space == "RGB":
        out = (1.0 - t)[:, None] * rgb0 + t[:, None] * rgb1
    elif space == "Step":
        out = rgb1.copy()
    elif space == "Lab":
        out = lab_to_rgb((1.0 - t)[:, None] * rgb_to_lab(rgb0) + t[:, None] * rgb_to_lab(rgb1))
    elif space == "HSV":
        out = interpolate_hsv(rgb0, rgb1, t, hsv_wrap)
    elif space == "Diverging":
        out = interpolate_diverging(rgb0, rgb1, t)
    else:
        raise ValueError(f"unknown colour space {space!r}: use one of {', '.join(SUPPORTED_COLOR_SPACES)}")
    return np.clip(out, 0.0, 1.0)
