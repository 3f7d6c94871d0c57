"""The viewer's time axis without a browser (issue 16): a time-series model opens at step 0, another step is
shown with the view kept, playing advances only once a step is rendered whole. Real data: a series model
trained on the four viscous-fingering steps of tests/data."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from apmgsrn.cli.main import main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.viewer.catalog import Catalog
from apmgsrn.viewer.session import ViewerSession
from apmgsrn.viewer.settings import ViewerConfig
from apmgsrn.viewer.timeline import Timeline

SMALL = ViewerConfig(image_width=40, image_height=32, samples_per_ray=32, batch_size=4096, chunk_pixels=256)


@pytest.fixture(scope="module")
def folder(tmp_path_factory, test_data):
    folder = tmp_path_factory.mktemp("viewer_series")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["train", str(test_data / "viscous_fingers_run01" / "*.vti"), "--out",
                     str(folder / "run.apmgsrn"), "--iterations", "120", "--batch-size", "2048", "--resolution", "8",
                     "--width", "32", "--device", "cpu"]) == 0
    finally:
        torch.set_num_threads(threads)
    return folder


def test_a_series_model_opens_at_step_0_and_shows_other_steps(folder):
    messages = []
    session = ViewerSession(Catalog(folder), "cpu", SMALL, on_message=lambda kind, payload: messages.append(kind))
    source = session.open_now("run.apmgsrn")
    assert source.series is not None and source.steps == 4 and source.step == 0
    assert source.step_labels == (30, 31, 32, 33) and "step 0 of 4 (number 30)" in source.description
    session.run_until_idle()
    first = session.last_frame.plain.copy()
    session.orbit(0.1, 0.0)
    session.end_interaction()
    timeline = Timeline(session)
    shown = timeline.show_step(3)
    assert shown is session.source and shown.step == 3 and "step 3 of 4 (number 33)" in shown.description
    session.run_until_idle()
    third = session.last_frame.plain
    assert session.last_frame.done and not np.array_equal(first, third)
    assert "step" in messages
    with pytest.raises(ApmgsrnError, match="time step 4 is outside 0..3"):
        timeline.request_step(4)


def test_the_view_is_kept_across_steps(folder):
    session = ViewerSession(Catalog(folder), "cpu", SMALL)
    session.open_now("run.apmgsrn")
    session.orbit(0.2, 0.1)
    before = session.camera()
    Timeline(session).show_step(2)
    after = session.camera()
    assert before.position == after.position and before.target == after.target


def test_playing_waits_for_a_whole_image_then_wraps_around(folder):
    session = ViewerSession(Catalog(folder), "cpu", SMALL)
    session.open_now("run.apmgsrn")
    timeline = Timeline(session, interval=0.5)
    assert timeline.next_step(now=100.0) is None  # not playing
    timeline.playing = True
    assert timeline.next_step(now=100.0) is None  # nothing rendered yet
    session.run_until_idle()
    assert timeline.next_step(now=100.0) == 1
    assert timeline.next_step(now=100.2) is None  # too soon after the last step
    timeline.show_step(3)
    session.run_until_idle()
    assert timeline.next_step(now=101.0) == 0  # the last step wraps to the first


def test_a_model_of_one_volume_has_no_time_axis(folder, test_data):
    assert main(["train", str(test_data / "neghip_64x64x64_uint8.raw"), "--out", str(folder / "one.apmgsrn"),
                 "--iterations", "20", "--batch-size", "1024", "--resolution", "8", "--device", "cpu"]) == 0
    session = ViewerSession(Catalog(folder), "cpu", SMALL)
    source = session.open_now("one.apmgsrn")
    assert source.series is None and source.steps == 1
    with pytest.raises(ApmgsrnError, match="no time steps"):
        Timeline(session).request_step(1)


def test_a_page_may_pick_only_a_whole_step_of_the_shown_series(folder):
    from apmgsrn.viewer.page_state import PageState

    session = ViewerSession(Catalog(folder), "cpu", SMALL)
    page = PageState(None, session, torch.device("cpu"))
    assert page.accepts("time_step", 0) and not page.accepts("time_step", 1)  # nothing shown: one step
    session.open_now("run.apmgsrn")
    assert page.accepts("time_step", 3) and page.accepts("time_step", 2.0)
    for bad in (4, -1, 1.5, True, "2", None, float("nan"), [1]):
        assert not page.accepts("time_step", bad), bad
    assert page.accepts("time_playing", True) and not page.accepts("time_playing", 1)
