"""Ray marching against analytic answers: Beer-Lambert, step-length invariance, skipping, batching."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from apmgsrn.rendering.camera import Camera, extent_from_shape
from apmgsrn.rendering.colormaps import make_transfer_function
from apmgsrn.rendering.bounds import ValueBounds
from apmgsrn.rendering.progressive import ProgressiveRender, pass_pixels, render_progressive, upsample
from apmgsrn.rendering.raymarch import RendererConfig, VolumeRenderer
from apmgsrn.rendering.transfer_function import ColorMap, OpacityMap, TransferFunction

COLOUR = (0.9, 0.3, 0.1)
BACKGROUND = (0.2, 0.4, 1.0)


def _flat_tf(opacity_at_one: float, opacity_at_zero: float = 0.0) -> TransferFunction:
    """One colour everywhere; opacity linear from value 0 to value 1."""
    return TransferFunction(
        color_map=ColorMap(points=((0.0, *COLOUR), (1.0, *COLOUR))),
        opacity_map=OpacityMap(((0.0, opacity_at_zero, 0.5, 0.0), (1.0, opacity_at_one, 0.5, 0.0))),
    )


def _constant_field(points: torch.Tensor) -> torch.Tensor:
    return torch.ones((points.shape[0], 1))


def _slab_field(points: torch.Tensor) -> torch.Tensor:
    return (points[:, 2:3].abs() < 0.5).float()


def _blobs(points: torch.Tensor) -> torch.Tensor:
    """A smooth field in [0, 1]: two Gaussian blobs."""
    a = torch.exp(-((points - torch.tensor([0.3, -0.2, 0.1])) ** 2).sum(1) / 0.25)
    b = torch.exp(-((points - torch.tensor([-0.4, 0.3, -0.3])) ** 2).sum(1) / 0.1)
    return (0.8 * a + 0.6 * b)[:, None]


def _random_rays(count: int, extent, seed: int = 0):
    """Rays from a sphere of radius 5 aimed at random points of the box."""
    gen = torch.Generator().manual_seed(seed)
    origins = torch.randn(count, 3, generator=gen, dtype=torch.float64)
    origins = 5.0 * origins / origins.norm(dim=1, keepdim=True)
    targets = (torch.rand(count, 3, generator=gen, dtype=torch.float64) * 2 - 1) * torch.tensor(extent) * 0.95
    directions = targets - origins
    return origins, directions / directions.norm(dim=1, keepdim=True)


def _chord(origins, directions, extent):
    e = torch.tensor(extent, dtype=torch.float64)
    t0, t1 = (-e - origins) / directions, (e - origins) / directions
    return (torch.minimum(t0, t1).amax(1).clamp(min=0) - torch.maximum(t0, t1).amin(1).clamp(min=0)).abs()


@pytest.mark.parametrize("extent", [(1.0, 1.0, 1.0), (1.0, 0.5, 0.25)])
@pytest.mark.parametrize("spp, jitter", [(7, False), (64, True), (256, False)])
def test_homogeneous_box_obeys_beer_lambert(extent, spp, jitter):
    a = 0.01
    config = RendererConfig(
        samples_per_ray=spp, early_termination=0.0, jitter=jitter, background=BACKGROUND, macro_cells=8
    )
    renderer = VolumeRenderer(_constant_field, _flat_tf(a), config, extent=extent)
    origins, directions = _random_rays(300, extent)
    colors, _ = renderer.render_rays(origins.float(), directions.float())
    length = _chord(origins, directions, extent)  # world units
    transmittance = (1 - a) ** (length / renderer.reference_step)  # opacity a per reference step
    expected = torch.tensor(COLOUR) * (1 - transmittance[:, None]) + torch.tensor(BACKGROUND) * transmittance[:, None]
    assert transmittance.min() < 0.2 and transmittance.max() > 0.5  # the rays span thin and thick chords
    torch.testing.assert_close(colors.double(), expected, atol=2e-5, rtol=0)


def test_slab_between_empty_space_obeys_beer_lambert():
    a = 0.02
    config = RendererConfig(samples_per_ray=512, early_termination=0.0, background=BACKGROUND, macro_cells=8)
    renderer = VolumeRenderer(_slab_field, _flat_tf(a, 0.0), config)
    # Straight through the slab |z| < 0.5 (thickness 1), and obliquely (thickness 1 / cos).
    xy = torch.rand(50, 2) * 1.6 - 0.8
    origins = torch.cat([xy, torch.full((50, 1), -3.0)], dim=1)
    down = torch.tensor([[0.0, 0.0, 1.0]]).expand(50, 3)
    colors, _ = renderer.render_rays(origins, down)
    t_expected = (1 - a) ** (1.0 / renderer.reference_step)
    expected = torch.tensor(COLOUR) * (1 - t_expected) + torch.tensor(BACKGROUND) * t_expected
    torch.testing.assert_close(colors, expected.expand(50, 3), atol=1e-5, rtol=0)
    tilt = math.radians(30)
    oblique = torch.tensor([[math.sin(tilt), 0.0, math.cos(tilt)]])
    origins = torch.tensor([[-0.5 - 3 * math.tan(tilt), 0.0, -3.0]])
    colors, _ = renderer.render_rays(origins, oblique)
    thickness = 1.0 / math.cos(tilt)
    # Blue channel: background * T, T known to within one step of path length.
    t_low = (1 - a) ** ((thickness + renderer.step) / renderer.reference_step)
    t_high = (1 - a) ** ((thickness - renderer.step) / renderer.reference_step)
    blue = (colors[0, 2] - COLOUR[2]) / (BACKGROUND[2] - COLOUR[2])
    assert t_low <= float(blue) <= t_high


def test_image_does_not_change_when_samples_per_ray_double():
    tf = make_transfer_function("viridis", (0.0, 0.8), opacity=((0.0, 0.0), (1.0, 0.25)))
    camera = Camera.orbit(width=40, height=40)
    images = {
        spp: VolumeRenderer(_blobs, tf, RendererConfig(samples_per_ray=spp, early_termination=0.0, macro_cells=8))
        .render(camera)
        .image
        for spp in (64, 128, 256)
    }
    assert (images[256] - 1.0).abs().mean() > 0.1  # a substantially opaque image, not the background
    assert (images[128] - images[256]).abs().max() < 1e-3
    assert (images[64] - images[256]).abs().max() < 2e-3
    # Without the correction each sample would take the table's opacity as is, which is what a reference
    # step equal to the step does: at 128 spp that image is visibly lighter than the corrected one.
    uncorrected = VolumeRenderer(
        _blobs, tf, RendererConfig(samples_per_ray=128, reference_samples=128, early_termination=0.0, macro_cells=8)
    ).render(camera).image
    assert (uncorrected - images[128]).abs().max() > 0.05


def test_skipping_leaves_the_raw_volume_image_unchanged(test_data):
    volume = np.fromfile(test_data / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    volume = volume.astype(np.float32)
    tf = make_transfer_function("plasma", (0.0, 255.0), opacity=((0.0, 0.0), (0.35, 0.0), (0.6, 0.6), (1.0, 0.9)))
    camera = Camera.orbit(azimuth=50, elevation=35, width=48, height=48)
    results = {}
    for skip in (False, True):
        config = RendererConfig(samples_per_ray=96, empty_space_skipping=skip, jitter=True, macro_cells=16)
        renderer = VolumeRenderer.for_volume(volume, tf, config)
        results[skip] = renderer.render(camera)
    assert (results[True].image - 1.0).abs().mean() > 0.02  # something is drawn
    torch.testing.assert_close(results[True].image, results[False].image, atol=1e-5, rtol=0)
    assert results[True].statistics.field_evaluations < 0.6 * results[False].statistics.field_evaluations
    assert results[True].statistics.samples_in_box == results[False].statistics.samples_in_box


def test_skipping_with_bounds_sampled_from_a_field_and_a_new_transfer_function():
    camera = Camera.orbit(azimuth=-20, width=40, height=40)
    narrow = make_transfer_function("coolwarm", (0.0, 0.8), opacity=((0.0, 0.0), (0.5, 0.0), (1.0, 0.8)))
    wide = make_transfer_function("coolwarm", (0.0, 0.8), opacity=((0.0, 0.0), (0.05, 0.0), (1.0, 0.3)))
    plain = VolumeRenderer(_blobs, narrow, RendererConfig(samples_per_ray=64, empty_space_skipping=False))
    skipping = VolumeRenderer(_blobs, narrow, RendererConfig(samples_per_ray=64, macro_cells=16))
    first = skipping.render(camera)
    assert skipping.bounds is not None and not skipping.bounds.exact
    torch.testing.assert_close(first.image, plain.render(camera).image, atol=1e-5, rtol=0)
    narrow_fraction = skipping.visible_fraction
    skipping.set_transfer_function(wide)  # re-classified, bounds kept
    plain.set_transfer_function(wide)
    assert skipping.visible_fraction > narrow_fraction
    second = skipping.render(camera)
    torch.testing.assert_close(second.image, plain.render(camera).image, atol=1e-5, rtol=0)
    assert first.statistics.field_evaluations < second.statistics.field_evaluations


def test_volume_bounds_contain_every_trilinear_value():
    gen = torch.Generator().manual_seed(3)
    z, y, x = torch.meshgrid(torch.linspace(0, 1, 13), torch.linspace(0, 1, 17), torch.linspace(0, 1, 21), indexing="ij")
    volume = torch.sin(3 * x + 2 * y) * z + 0.05 * torch.rand(13, 17, 21, generator=gen)  # smooth plus noise
    bounds = ValueBounds.from_volume(volume, cells=5)
    assert bounds.cells == (5, 5, 5) and bounds.exact
    from apmgsrn.ops.trilinear import sample_volume

    points = torch.rand(20000, 3, generator=gen) * 2 - 1
    values = sample_volume(volume, points)
    cell = ((points + 1) / 2 * 5).floor().long().clamp(0, 4)  # (x, y, z)
    low = bounds.low[cell[:, 2], cell[:, 1], cell[:, 0]]
    high = bounds.high[cell[:, 2], cell[:, 1], cell[:, 0]]
    assert (values >= low).all() and (values <= high).all()
    assert (high - low).mean() < 0.5 * (volume.max() - volume.min())  # much tighter than the global range


def test_early_termination_changes_little_and_saves_work():
    tf = make_transfer_function("grayscale", (0.0, 0.8), opacity=((0.0, 0.0), (1.0, 1.0)))
    camera = Camera.orbit(width=32, height=32)
    full = VolumeRenderer(_blobs, tf, RendererConfig(samples_per_ray=128, early_termination=0.0)).render(camera)
    early = VolumeRenderer(_blobs, tf, RendererConfig(samples_per_ray=128, early_termination=1e-2)).render(camera)
    assert (full.image - early.image).abs().max() < 1.1e-2
    assert early.statistics.field_evaluations < 0.9 * full.statistics.field_evaluations


def test_field_never_sees_more_than_the_batch_size():
    seen = []

    def counting_field(points):
        seen.append(points.shape[0])
        return _blobs(points)

    tf = make_transfer_function("viridis", (0.0, 0.8), opacity=((0.0, 0.0), (0.2, 0.0), (1.0, 0.5)))
    camera = Camera.orbit(width=36, height=28)
    small = VolumeRenderer(counting_field, tf, RendererConfig(samples_per_ray=64, batch_size=300, macro_cells=8))
    image_small = small.render(camera).image
    assert max(seen) <= 300 and len(seen) > 10
    large = VolumeRenderer(_blobs, tf, RendererConfig(samples_per_ray=64, batch_size=1 << 16, macro_cells=8))
    torch.testing.assert_close(image_small, large.render(camera).image, atol=1e-5, rtol=0)


def test_progressive_passes_partition_the_image_and_end_with_the_full_render():
    passes = pass_pixels(13, 10, (8, 4, 2, 1))
    every = torch.cat(passes)
    assert every.numel() == 130 and every.unique().numel() == 130
    assert passes[0].tolist() == [0, 8, 104, 112]  # rows 0 and 8, columns 0 and 8
    tf = make_transfer_function("magma", (0.0, 0.8), opacity=((0.0, 0.0), (1.0, 0.4)))
    renderer = VolumeRenderer(_blobs, tf, RendererConfig(samples_per_ray=48, jitter=True))
    camera = Camera.orbit(width=24, height=20)
    frames = list(render_progressive(renderer, camera))
    assert [f.stride for f in frames] == [8, 4, 2, 1] and frames[-1].done
    assert frames[0].pixels_rendered == 3 * 3 and frames[-1].pixels_rendered == 480
    assert frames[0].statistics.rays == 9
    for frame in frames:
        assert frame.image.shape == (20, 24, 3)
    full = renderer.render(camera).image
    # The coarse image holds the rendered lattice pixels and interpolates between them.
    assert torch.equal(frames[0].image[::8, ::8], full[::8, ::8])
    torch.testing.assert_close(frames[0].image[4, 4], full[[0, 0, 8, 8], [0, 8, 0, 8]].mean(0), atol=1e-6, rtol=0)
    torch.testing.assert_close(frames[-1].image, full, atol=0, rtol=0)


def test_a_pass_rendered_in_chunks_equals_the_pass_rendered_at_once():
    tf = make_transfer_function("viridis", (0.0, 0.8), opacity=((0.0, 0.0), (1.0, 0.5)))
    renderer = VolumeRenderer(_blobs, tf, RendererConfig(samples_per_ray=32))
    camera = Camera.orbit(width=21, height=17)
    chunked = ProgressiveRender(renderer, camera)
    images = []
    while not chunked.done:
        pixels = chunked.next_pixels
        work = sum(chunked.render_pixels(pixels[start : start + 7]).rays for start in range(0, pixels.numel(), 7))
        assert work == pixels.numel()
        images.append(chunked.finish_pass())
    at_once = list(ProgressiveRender(renderer, camera))
    for a, b in zip(images, at_once, strict=True):
        # Up to float rounding: vectorised exp rounds the tail of an array its own way.
        torch.testing.assert_close(a.image, b.image, atol=1e-6, rtol=0)
        assert a.statistics.rays == b.statistics.rays and a.stride == b.stride


def test_bilinear_upsampling_keeps_the_lattice_and_reproduces_a_linear_image():
    rows = torch.arange(10, dtype=torch.float32)[:, None, None]
    cols = torch.arange(13, dtype=torch.float32)[None, :, None]
    image = (0.02 * rows + 0.03 * cols).expand(10, 13, 3).contiguous()
    up = upsample(image, 4)
    assert torch.equal(up[::4, ::4], image[::4, ::4])
    assert torch.allclose(up[:9, :13 - 1], image[:9, :13 - 1], atol=1e-6)  # rows 0..8 and cols 0..11: inside
    assert torch.equal(up[9], up[8])  # past the last lattice row: held
    assert torch.equal(upsample(image, 1), image)


def test_orbit_camera_conventions():
    camera = Camera.orbit(azimuth=0, elevation=0, distance=4, width=3, height=3)
    assert camera.position == pytest.approx((0.0, -4.0, 0.0))
    origins, directions = camera.rays(torch.arange(9))
    torch.testing.assert_close(directions[4], torch.tensor([0.0, 1.0, 0.0]))  # centre pixel looks at the target
    assert directions[5, 0] > 0 and directions[1, 2] > 0  # right is +x, up is +z
    top = Camera.orbit(azimuth=0, elevation=90, distance=4, width=3, height=3)
    _, d = top.rays(torch.tensor([4]))
    torch.testing.assert_close(d[0], torch.tensor([0.0, 0.0, -1.0]), atol=1e-6, rtol=0)
    assert extent_from_shape((48, 240, 640)) == pytest.approx((1.0, 239 / 639, 47 / 639))


@pytest.mark.gpu
def test_cuda_render_matches_cpu():
    tf = make_transfer_function("viridis", (0.0, 0.8), opacity=((0.0, 0.0), (0.2, 0.0), (1.0, 0.5)))
    camera = Camera.orbit(width=48, height=48)

    def field_on(device):
        centre_a = torch.tensor([0.3, -0.2, 0.1], device=device)
        centre_b = torch.tensor([-0.4, 0.3, -0.3], device=device)

        def field(points):
            a = torch.exp(-((points - centre_a) ** 2).sum(1) / 0.25)
            b = torch.exp(-((points - centre_b) ** 2).sum(1) / 0.1)
            return (0.8 * a + 0.6 * b)[:, None]

        return field

    cpu = VolumeRenderer(field_on("cpu"), tf, RendererConfig(samples_per_ray=64), device="cpu").render(camera)
    gpu = VolumeRenderer(field_on("cuda"), tf, RendererConfig(samples_per_ray=64), device="cuda").render(camera)
    torch.testing.assert_close(gpu.image, cpu.image, atol=1e-4, rtol=0)
