"""The viewer's session without a browser: camera control, progressive passes, stale-pass dropping,
interactive budget, settings, presets, overlay and a model that fails to load."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from viewer_data import make_viewer_folder

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering import Camera, RendererConfig
from apmgsrn.viewer.catalog import Catalog
from apmgsrn.viewer.orbit import OrbitView
from apmgsrn.viewer.session import ViewerSession
from apmgsrn.viewer.settings import ViewerConfig

SMALL = ViewerConfig(image_width=40, image_height=32, samples_per_ray=32, batch_size=4096, chunk_pixels=256)


class Recorder:
    """Collects frames and messages; optionally acts on the n-th frame (a user moving mid-render)."""

    def __init__(self):
        self.frames = []
        self.messages = []
        self.on_nth = {}

    def frame(self, frame):
        self.frames.append(frame)
        action = self.on_nth.pop(len(self.frames), None)
        if action is not None:
            action()

    def message(self, kind, payload):
        self.messages.append((kind, payload))


@pytest.fixture()
def folder(tmp_path):
    return make_viewer_folder(tmp_path)


def _session(folder, config=SMALL):
    recorder = Recorder()
    session = ViewerSession(Catalog(folder), "cpu", config, on_frame=recorder.frame, on_message=recorder.message)
    return session, recorder


# ------------------------------------------------------------------------------------------ camera
def test_orbit_view_turns_pans_and_zooms():
    view = OrbitView()
    extent = (1.0, 0.5, 0.75)
    start = view.camera(64, 48, extent)
    # Dragging right turns the camera the other way round (the object follows the pointer).
    assert view.orbited(0.1, 0.0).azimuth == pytest.approx(view.azimuth - 18.0)
    assert view.orbited(0.0, 10.0).elevation == 89.5  # clamped short of the pole
    # Zoom multiplies the fitted distance; limits hold.
    closer = view.zoomed(-1.0).camera(64, 48, extent)
    assert math.dist(closer.position, closer.target) == pytest.approx(math.dist(start.position, start.target) / 1.1)
    assert view.zoomed(1e6).distance_scale == OrbitView.MAX_DISTANCE_SCALE
    # Panning slides the target across the view, never along it; dragging right moves the target left.
    panned = view.panned(0.25, 0.0, 64, 48, extent)
    forward, right, _ = start.basis()
    shift = torch.tensor(panned.target, dtype=torch.float64)
    assert float(shift @ forward) == pytest.approx(0.0, abs=1e-9)
    assert float(shift @ right) < 0
    moved = panned.camera(64, 48, extent)
    assert np.allclose(np.subtract(moved.position, moved.target), np.subtract(start.position, start.target))


# ------------------------------------------------------------------------------------------ rendering
def test_progressive_passes_end_in_the_exact_render(folder):
    session, recorder = _session(folder)
    source = session.open_now("a_blob.npy")
    session.run_until_idle()
    strides = [frame.stride for frame in recorder.frames]
    assert strides == [8, 4, 2, 1]
    final = recorder.frames[-1]
    assert final.done and final.generation == session.generation
    reference = source.renderer(
        session.transfer_function(), RendererConfig(samples_per_ray=32, batch_size=4096, macro_cells=16)
    ).render(session.camera())
    expected = (reference.image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    assert np.abs(final.image.astype(int) - expected.astype(int)).max() <= 1
    assert expected.std() > 5  # the blobs are visible, not a blank image
    stats = session.statistics()
    assert stats.passes_done == 4 and stats.last_frame_seconds is not None
    assert "MiB" in stats.memory


def test_a_camera_change_between_passes_drops_the_old_generation(folder):
    session, recorder = _session(folder)
    session.open_now("a_blob.npy")
    recorder.on_nth[2] = lambda: (session.orbit(0.2, 0.0), session.end_interaction())
    session.run_until_idle()
    generations = [frame.generation for frame in recorder.frames]
    assert generations == sorted(generations)
    changed_at = generations[1]
    # After the second frame the camera moved: nothing of that generation was handed out any more.
    assert generations[2:] and all(g > changed_at for g in generations[2:])
    assert recorder.frames[-1].done and recorder.frames[-1].generation == session.generation
    assert recorder.frames[-1].camera == session.camera()


def test_a_camera_change_during_a_pass_abandons_it(folder):
    session, recorder = _session(folder)
    source = session.open_now("a_blob.npy")
    session.run_until_idle()
    done_generation = session.generation
    calls = {"count": 0, "frames_before": None}
    inner = source.field

    def field_that_sees_the_user_move(points):
        calls["count"] += 1
        if calls["count"] == 3:  # in the middle of a pass of the next generation
            calls["frames_before"] = len(recorder.frames)
            session.orbit(-0.1, 0.05)
            session.end_interaction()
        return inner(points)

    session.worker.renderer.field = field_that_sees_the_user_move  # the renderer's public attribute
    recorder.frames.clear()
    session.orbit(0.1, 0.0)
    session.end_interaction()
    moved_generation = session.generation
    session.run_until_idle()
    assert calls["count"] >= 3
    before, after = recorder.frames[: calls["frames_before"]], recorder.frames[calls["frames_before"] :]
    assert all(frame.generation == moved_generation and not frame.done for frame in before)
    # The pass in flight was abandoned: nothing of the moved generation came out after the change.
    assert after and all(frame.generation > moved_generation for frame in after)
    assert done_generation < moved_generation
    assert recorder.frames[-1].done and recorder.frames[-1].generation == session.generation


def test_while_moving_only_the_budgeted_passes_render_then_it_refines(folder):
    config = ViewerConfig(
        image_width=40, image_height=32, samples_per_ray=32, batch_size=4096,
        interactive_seconds=0.0, rest_seconds=60.0,
    )
    session, recorder = _session(folder, config)
    session.open_now("a_blob.npy")
    session.run_until_idle()
    recorder.frames.clear()
    session.orbit(0.05, 0.0)  # moving: within rest_seconds of a camera event
    assert session.step()
    assert not session.step()  # the coarse image is out, nothing more while the view moves
    assert [(f.stride, f.moving) for f in recorder.frames] == [(8, True)]
    session.end_interaction()  # pointer released: refine the same generation
    session.run_until_idle()
    assert [f.stride for f in recorder.frames] == [8, 4, 2, 1]
    assert len({f.generation for f in recorder.frames}) == 1


def test_settings_change_the_image_and_bad_values_are_refused(folder):
    session, recorder = _session(folder)
    session.open_now("a_blob.npy")
    session.run_until_idle()
    first = recorder.frames[-1].image
    session.set_colormap("grayscale")
    session.run_until_idle()
    gray = recorder.frames[-1].image
    assert not np.array_equal(gray, first)
    assert np.abs(gray[..., 0].astype(int) - gray[..., 2].astype(int)).max() <= 1  # a gray ramp
    session.set_opacity([[1.0, 0.0], [0.0, 0.0]])  # all transparent: background only
    session.run_until_idle()
    assert (recorder.frames[-1].image == 255).all()
    session.set_image_size(24, 20)
    session.run_until_idle()
    assert recorder.frames[-1].image.shape == (20, 24, 3)
    for bad in (
        lambda: session.set_colormap("no such map"),
        lambda: session.set_value_range(2.0, 1.0),
        lambda: session.set_value_range(float("nan"), 1.0),
        lambda: session.set_opacity([]),
        lambda: session.set_opacity([[0.0, "x"]]),
        lambda: session.set_samples_per_ray(0),
        lambda: session.set_batch_size(8),
        lambda: session.set_image_size(10_000, 10),
    ):
        with pytest.raises(ApmgsrnError):
            bad()


def test_presets_in_the_folder_bring_their_colours_and_opacity(folder):
    session, recorder = _session(folder)
    keys = session.add_presets(folder / "reds.json", "reds.json")
    assert keys == ["Two Reds (reds.json)"]
    session.open_now("a_blob.npy")
    opacity = session.set_colormap(keys[0])
    assert opacity == [[0.0, 0.0], [0.5, 0.1], [1.0, 0.9]]
    session.run_until_idle()
    image = recorder.frames[-1].image.astype(int)
    tinted = (image[..., 0] - image[..., 2]) > 20
    assert tinted.any()  # red where the blobs are


# Opacity nodes on another span than the colours, with ParaView's midpoint and sharpness; and a preset
# spaced in log10. ParaView stretches each map by its own span (the log one in log10).
UNEVEN_PRESETS = [
    {
        "Name": "Uneven",
        "ColorSpace": "Lab",
        "RGBPoints": [-1.0, 0.1, 0.2, 0.7, 1.0, 0.9, 0.9, 0.9, 3.0, 0.8, 0.1, 0.1],
        "Points": [0.0, 0.0, 0.3, 0.6, 0.5, 0.4, 0.5, 0.0, 2.0, 0.9, 0.7, 0.2],
    },
    {
        "Name": "Decades",
        "ColorSpace": "RGB",
        "UseLogScale": 1,
        "RGBPoints": [1.0, 0.0, 0.0, 0.0, 10.0, 0.2, 0.6, 0.2, 100.0, 1.0, 1.0, 1.0],
        "Points": [10.0, 0.0, 0.5, 0.0, 100.0, 0.3, 0.4, 0.1, 1000.0, 1.0, 0.5, 0.0],
    },
]


def test_presets_apply_exactly_as_the_render_command_applies_them(folder):
    import json

    from apmgsrn.rendering import make_transfer_function

    path = folder / "uneven.json"
    path.write_text(json.dumps(UNEVEN_PRESETS), encoding="utf-8")
    session, _ = _session(folder)
    keys = session.add_presets(path, "uneven.json")
    session.open_now("a_blob.npy")
    for key, preset in zip(keys, UNEVEN_PRESETS):
        session.set_colormap(key)
        low, high = session.settings.value_range
        viewer = session.transfer_function()
        # What 'apmgsrn render --colormap uneven.json --preset-name NAME' draws over the same range.
        render = make_transfer_function(str(path), (low, high), preset_name=preset["Name"])
        assert viewer.color_map.points == render.color_map.points
        assert viewer.color_map.color_space == render.color_map.color_space
        assert viewer.opacity_map.points == render.opacity_map.points  # positions, midpoints and sharpness
        np.testing.assert_array_equal(viewer.table(256).opacity.numpy(), render.table(256).opacity.numpy())
        np.testing.assert_array_equal(viewer.table(256).colors.numpy(), render.table(256).colors.numpy())


def test_overlay_draws_grid_boxes_of_a_model_and_can_be_removed(folder):
    session, recorder = _session(folder)
    source = session.open_now("tiny.apmgsrn")
    assert source.grid_boxes is not None and source.grid_boxes.shape == (2, 8, 3)
    session.run_until_idle()
    plain = recorder.frames[-1].image
    session.set_overlay(True)
    session.run_until_idle()
    boxed = recorder.frames[-1].image
    assert not np.array_equal(boxed, plain)
    assert recorder.frames[-1].generation == recorder.frames[-2].generation  # redrawn, not re-rendered
    session.set_overlay(False)
    session.run_until_idle()
    assert np.array_equal(recorder.frames[-1].image, plain)


def test_a_model_that_fails_to_load_reports_and_keeps_the_current_view(folder):
    session, recorder = _session(folder)
    session.open_now("a_blob.npy")
    session.run_until_idle()
    session.request_open("broken.apmgsrn")
    session.run_until_idle()
    errors = [payload for kind, payload in recorder.messages if kind == "error"]
    assert errors and "broken.apmgsrn" in errors[-1]
    assert session.source.name == "a_blob.npy"
    session.orbit(0.1, 0.1)
    session.end_interaction()
    session.run_until_idle()
    assert recorder.frames[-1].done  # still rendering
    with pytest.raises(ApmgsrnError, match="refused"):
        session.request_open("../secret.npy")


def test_worker_thread_renders_and_stops(folder):
    session, recorder = _session(folder)
    session.start()
    try:
        session.request_open("a_blob.npy")
        deadline = 60.0
        import time

        start = time.monotonic()
        while not (recorder.frames and recorder.frames[-1].done) and time.monotonic() - start < deadline:
            time.sleep(0.02)
        assert recorder.frames and recorder.frames[-1].done
    finally:
        session.stop()
    assert session.worker._thread is None


def test_cameras_match_the_render_module_convention():
    # The default view is Camera.orbit's default: the viewer and 'apmgsrn render' agree on angles.
    view_camera = OrbitView().camera(50, 40, (1.0, 1.0, 1.0))
    render_camera = Camera.orbit(width=50, height=40)
    assert np.allclose(view_camera.position, render_camera.position)
