"""Renders must not change: the library, ``apmgsrn render`` and the viewer draw the same pixels as main at
50ca313 did (before the renderer was split into stages) for a real volume, a tiny trained model and a
tiny brick model, bit for bit on a CPU. The reference images and how they were made: ``render_reference.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from render_reference import REFERENCE, cli_images, library_images, viewer_images

pytestmark = pytest.mark.usefixtures("one_thread")  # the references were rendered on one thread


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE) as stored:
        return {name: stored[name] for name in stored.files}


def _assert_same(images: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> None:
    for name, image in images.items():
        expected = reference[name]
        assert image.dtype == expected.dtype and image.shape == expected.shape, name
        if image.dtype == np.uint8:
            assert np.array_equal(image, expected), f"{name}: {np.abs(image.astype(float) - expected).max()} off"
        else:  # float images of a model: the fused CPU decoder sums in its own order (float32 rounding)
            off = np.abs(image.astype(np.float64) - expected).max()
            assert off <= 1e-6, f"{name}: {off} off"
        assert expected.astype(np.float64).std() > 0.03 * (255 if expected.dtype == np.uint8 else 1)  # not blank


def test_library_renders_are_unchanged(reference):
    images = library_images()
    assert {name for name in reference if not name.startswith(("cli_", "viewer_"))} == set(images)
    _assert_same(images, reference)
    # A progressive render ends in the full render (up to float rounding: the network sees other batches),
    # and the brick model is not the single model.
    np.testing.assert_allclose(images["model_progressive_final"], images["model"], atol=1e-6, rtol=0)
    assert not np.array_equal(images["bricks"], images["model"])


def test_cli_renders_are_unchanged(reference, tmp_path, capsys):
    _assert_same(cli_images(tmp_path), reference)


def test_viewer_frames_are_unchanged(reference, tmp_path):
    images = viewer_images(tmp_path)
    _assert_same(images, reference)
    # The overlay draws the grid boxes of the models; a volume has none.
    assert np.array_equal(images["viewer_volume_overlay"], images["viewer_volume"])
    assert not np.array_equal(images["viewer_model_overlay"], images["viewer_model"])
    assert torch.get_num_threads() == 1
