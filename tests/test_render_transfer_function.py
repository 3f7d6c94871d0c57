"""Transfer functions: colour spaces, ParaView's opacity curve, the baked table and its zero test."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.color_spaces import hsv_to_rgb, lab_to_rgb, rgb_to_hsv, rgb_to_lab
from apmgsrn.rendering.colormaps import COOL_TO_WARM, builtin_colormap, make_transfer_function
from apmgsrn.rendering.transfer_function import (
    ColorMap,
    OpacityMap,
    TransferFunction,
    opacity_from_normalized,
)


def test_lab_and_hsv_round_trip_and_reference_values():
    rng = np.random.default_rng(0)
    rgb = rng.random((200, 3))
    # VTK's (and so ParaView's) sRGB <-> XYZ matrices are rounded to four digits and not exact inverses:
    # a round trip moves a colour by up to a few 1e-4, well inside one 8-bit step (1/255 = 0.0039).
    np.testing.assert_allclose(lab_to_rgb(rgb_to_lab(rgb)), rgb, atol=5e-4)
    np.testing.assert_allclose(hsv_to_rgb(rgb_to_hsv(rgb)), rgb, atol=1e-9)
    # Published CIE Lab (D65) values of sRGB white, red and a mid grey.
    np.testing.assert_allclose(rgb_to_lab(np.array([1.0, 1.0, 1.0])), [100.0, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(rgb_to_lab(np.array([1.0, 0.0, 0.0])), [53.24, 80.09, 67.20], atol=0.05)
    np.testing.assert_allclose(rgb_to_lab(np.array([0.5, 0.5, 0.5]))[0], 53.39, atol=0.05)


def test_rgb_interpolation_is_linear_and_clamps_outside():
    cmap = ColorMap(points=((0.0, 0.0, 0.0, 0.0), (2.0, 1.0, 0.5, 0.0)), color_space="RGB")
    out = cmap.evaluate(np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0]))
    np.testing.assert_allclose(out[:, 0], [0.0, 0.0, 0.25, 0.5, 1.0, 1.0])
    np.testing.assert_allclose(out[:, 1], [0.0, 0.0, 0.125, 0.25, 0.5, 0.5])


def test_lab_interpolation_is_linear_in_lab_not_rgb():
    cmap = ColorMap(points=((0.0, 0.0, 0.0, 1.0), (1.0, 1.0, 1.0, 0.0)), color_space="Lab")
    mid = cmap.evaluate(np.array([0.5]))[0]
    expected = lab_to_rgb((rgb_to_lab(np.array([0.0, 0.0, 1.0])) + rgb_to_lab(np.array([1.0, 1.0, 0.0]))) / 2)
    np.testing.assert_allclose(mid, expected, atol=1e-9)
    assert np.abs(mid - 0.5).max() > 0.05  # differs from the RGB midpoint


def test_cool_to_warm_matches_paraview():
    # ParaView's default map: blue (59, 76, 192) to red (180, 4, 38) through a light grey centre.
    ends = COOL_TO_WARM.evaluate(np.array([0.0, 1.0]))
    np.testing.assert_allclose(ends * 255, [[59, 76, 192], [180, 4, 38]], atol=0.5)
    mid = COOL_TO_WARM.evaluate(np.array([0.5]))[0]
    np.testing.assert_allclose(mid, [0.865, 0.865, 0.865], atol=0.01)
    # The diverging path stays saturated on each side: the quarter point is clearly blue.
    quarter = COOL_TO_WARM.evaluate(np.array([0.25]))[0]
    assert quarter[2] > quarter[0] + 0.15


def test_hsv_interpolation_goes_round_the_short_way_only_with_hsv_wrap():
    # Hue 1 - 0.2/6 (red-magenta) down to 0 (red). ParaView applies presets with HSVWrap off: the hue
    # runs down through blue and green, reaching 1/3 (pure green here) at t = 1 - (1/3) / hue0.
    hue0 = 1.0 - 0.2 / 6.0
    straight = ColorMap(points=((0.0, 1.0, 0.0, 0.2), (1.0, 1.0, 0.0, 0.0)), color_space="HSV")
    out = straight.evaluate(np.array([0.0, 1.0 - (1.0 / 3.0) / hue0, 1.0]))
    np.testing.assert_allclose(out, [[1.0, 0.0, 0.2], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], atol=1e-12)
    # With HSVWrap the short path stays red-magenta and never passes through green.
    wrapped = ColorMap(points=straight.points, color_space="HSV", hsv_wrap=True)
    assert (wrapped.evaluate(np.linspace(0.0, 1.0, 11))[:, 1] < 0.01).all()


def test_blue_to_red_hsv_passes_green_at_the_middle():
    # ParaView's "Blue to Red Rainbow": blue (hue 2/3) to red (hue 0) in HSV, no wrap: green half way.
    rainbow = ColorMap(points=((0.0, 0.0, 0.0, 1.0), (1.0, 1.0, 0.0, 0.0)), color_space="HSV")
    np.testing.assert_allclose(rainbow.evaluate(np.array([0.5]))[0], [0.0, 1.0, 0.0], atol=1e-12)


def test_step_takes_the_upper_node_and_shared_positions_keep_their_order():
    step = ColorMap(points=((0.0, 1.0, 0.0, 0.0), (1.0, 0.0, 1.0, 0.0), (2.0, 0.0, 0.0, 1.0)), color_space="Step")
    out = step.evaluate(np.array([-1.0, 0.0, 1e-9, 1.0, 1.5, 2.0, 3.0]))
    # VTK: at or below the first node its colour; in (x_k-1, x_k] the colour of node k; beyond, the last.
    np.testing.assert_array_equal(out, [[1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 0, 1]])
    # Two nodes at 1.0 (a sharp change): the first colours 1.0 itself and below, the second above.
    ties = ColorMap(points=((0.0, 0.0, 0.0, 0.0), (1.0, 1.0, 0.0, 0.0), (1.0, 0.0, 0.0, 1.0), (2.0, 0.0, 0.0, 0.0)))
    np.testing.assert_allclose(ties.evaluate(np.array([0.5, 1.0, 1.5])), [[0.5, 0, 0], [1, 0, 0], [0, 0, 0.5]])


def test_log_scale_interpolates_in_log10_and_rescales_by_decades():
    grey = ColorMap(points=((1.0, 0.0, 0.0, 0.0), (100.0, 1.0, 1.0, 1.0)), log_scale=True)
    np.testing.assert_allclose(grey.evaluate(np.array([10.0, 10**1.5]))[:, 0], [0.5, 0.75], atol=1e-12)
    # Rescaled to 0.1..1000, 10 (one decade of two) lands on the middle of four decades: 10.
    moved = grey.rescaled(0.1, 1000.0)
    assert moved.span == pytest.approx((0.1, 1000.0))
    np.testing.assert_allclose(moved.evaluate(np.array([10.0]))[0], [0.5] * 3, atol=1e-12)
    with pytest.raises(ApmgsrnError, match="log scale"):
        grey.rescaled(-1.0, 10.0)


def test_builtin_colormaps_exist_and_span_unit_interval():
    for name in ("viridis", "plasma", "coolwarm", "grayscale", "jet", "Cool to Warm", "Viridis (matplotlib)"):
        cmap = builtin_colormap(name)
        assert cmap.span == (0.0, 1.0)
        colors = cmap.evaluate(np.linspace(0, 1, 5))
        assert colors.shape == (5, 3) and (colors >= 0).all() and (colors <= 1).all()
    np.testing.assert_allclose(builtin_colormap("viridis").evaluate(np.array([0.0]))[0], [0.267, 0.005, 0.329], atol=2e-3)
    with pytest.raises(ApmgsrnError, match="unknown colour map"):
        builtin_colormap("no-such-map")


def test_opacity_midpoint_and_sharpness_follow_vtk():
    linear = OpacityMap(((0.0, 0.0, 0.5, 0.0), (1.0, 1.0, 0.5, 0.0)))
    np.testing.assert_allclose(linear.evaluate(np.array([0.0, 0.3, 1.0])), [0.0, 0.3, 1.0])
    shifted = OpacityMap(((0.0, 0.0, 0.25, 0.0), (1.0, 1.0, 0.5, 0.0)))
    # Half way reached at the midpoint 0.25, linear on each side of it.
    np.testing.assert_allclose(shifted.evaluate(np.array([0.125, 0.25, 0.625])), [0.25, 0.5, 0.75])
    step = OpacityMap(((0.0, 0.2, 0.5, 1.0), (1.0, 0.8, 0.5, 0.0)))
    np.testing.assert_allclose(step.evaluate(np.array([0.1, 0.49, 0.51, 0.9])), [0.2, 0.2, 0.8, 0.8])
    soft = OpacityMap(((0.0, 0.0, 0.5, 0.5), (1.0, 1.0, 0.5, 0.0)))
    values = soft.evaluate(np.linspace(0, 1, 101))
    assert np.all(np.diff(values) >= -1e-12)  # monotone between nodes
    assert values[50] == pytest.approx(0.5, abs=1e-9)
    assert values[25] < 0.25  # flatter near the ends than linear


def test_rescale_moves_colour_and_opacity_nodes_together():
    tf = TransferFunction(
        color_map=builtin_colormap("grayscale"),
        opacity_map=opacity_from_normalized(((0.0, 0.0), (0.5, 0.2), (1.0, 1.0)), (0.0, 1.0)),
    ).rescaled(10.0, 30.0)
    assert tf.value_range == (10.0, 30.0)
    assert [p[0] for p in tf.opacity_map.points] == [10.0, 20.0, 30.0]
    np.testing.assert_allclose(tf.color_map.evaluate(np.array([20.0])), [[0.5, 0.5, 0.5]])


def test_table_lookup_matches_the_transfer_function_at_its_entries():
    tf = make_transfer_function("Cool to Warm", (-2.0, 6.0), opacity=((0.0, 0.0), (0.4, 0.0), (1.0, 0.7)))
    table = tf.table(size=257)
    xs = np.linspace(-2.0, 6.0, 257)
    colors, opacity = table.lookup(torch.tensor(xs, dtype=torch.float32))
    np.testing.assert_allclose(colors.numpy(), tf.color_map.evaluate(xs), atol=1e-5)
    np.testing.assert_allclose(opacity.numpy(), tf.opacity_map.evaluate(xs), atol=1e-5)
    # Clamped beyond the range, NaN gets the NaN colour and opacity.
    colors, opacity = table.lookup(torch.tensor([-100.0, 100.0, float("nan")]))
    np.testing.assert_allclose(colors[0].numpy(), tf.color_map.evaluate(np.array([-2.0]))[0], atol=1e-5)
    assert opacity[1] == pytest.approx(0.7)
    assert opacity[2] == 0.0 and torch.allclose(colors[2], torch.tensor([1.0, 1.0, 0.0]))


def test_zero_opacity_test_never_misses_a_visible_value():
    tf = make_transfer_function("viridis", (0.0, 1.0), opacity=((0.0, 0.0), (0.3, 0.0), (0.5, 0.4), (0.6, 0.0), (1.0, 0.0)))
    table = tf.table(size=512)
    gen = torch.Generator().manual_seed(1)
    lows = torch.rand(4000, generator=gen) * 1.2 - 0.1
    highs = lows + torch.rand(4000, generator=gen) * 0.3
    visible = table.opacity_nonzero_between(lows, highs)
    # Brute force: dense values in each interval through the very lookup the renderer uses.
    t = torch.linspace(0, 1, 200)
    values = lows[:, None] + (highs - lows)[:, None] * t  # [4000, 200]
    _, alpha = table.lookup(values.reshape(-1))
    truly_visible = (alpha.view(4000, 200) > 0).any(dim=1)
    assert not (truly_visible & ~visible).any()  # no false "transparent"
    # ...and the test is tight: intervals well inside the transparent band are skipped.
    assert not table.opacity_nonzero_between(torch.tensor([0.05, 0.7]), torch.tensor([0.25, 0.95])).any()
    assert table.opacity_nonzero_between(torch.tensor([0.25]), torch.tensor([0.35])).all()
