"""Grid pictures: streamed projections, the VTK boxes ParaView reads, the picture and the animation."""

import numpy as np
import pytest
import torch
from PIL import Image

import apmgsrn
from apmgsrn.bench.grid_pictures import convex_hull, projections, record_grid_history
from apmgsrn.cli.main import main
from apmgsrn.data import ArrayVolume, open_volume


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def trained(hcci_oh, tmp_path_factory):
    """A real 24x28x32 (z, y, x) crop of the hcci OH field and an APMGSRN model of it after 12 iterations.

    The density step starts at iteration 1 (5 % of 12), so the grids have moved.
    """
    folder = tmp_path_factory.mktemp("grids")
    data = open_volume(hcci_oh, variable="oh").read(
        slice(70, 94), slice(70, 98), slice(70, 102)
    )
    path = folder / "hcci_crop.npy"
    np.save(path, data)
    model = folder / "m.apmgsrn"
    assert main(["train", str(path), "--out", str(model), "--iterations", "12", "--batch-size", "1024",
                 "--device", "cpu"]) == 0
    return path, data, model


def test_projections_stream_over_slabs_and_match_the_whole_array(trained):
    _, data, _ = trained
    mips = projections(ArrayVolume(data), slab_voxels=28 * 32 * 5)  # 5 z-slices per slab: 5 slabs
    np.testing.assert_array_equal(mips.along_z, data.max(axis=0))
    np.testing.assert_array_equal(mips.along_y, data.max(axis=1))
    np.testing.assert_array_equal(mips.along_x, data.max(axis=2))


def test_grids_command_writes_picture_and_vtk_boxes_in_voxel_coordinates(trained, tmp_path, capsys):
    vtk = pytest.importorskip("vtk")
    path, data, model = trained
    prefix = tmp_path / "boxes"
    assert main(["grids", str(model), str(path), "--out", str(prefix)]) == 0
    with Image.open(f"{prefix}.png") as picture:
        assert picture.format == "PNG" and picture.width > 2 * picture.height

    reader = vtk.vtkUnstructuredGridReader()
    reader.SetFileName(f"{prefix}.vtk")
    reader.Update()
    grid = reader.GetOutput()
    boxes = apmgsrn.load(model).field.encoder.grid_boxes().double().numpy()  # [M, 8, 3] in [-1, 1]
    count = boxes.shape[0]
    assert count == 8 and grid.GetNumberOfCells() == count  # the default model's adaptive grids
    assert {grid.GetCellType(i) for i in range(count)} == {vtk.VTK_HEXAHEDRON}
    d, h, w = data.shape
    expected = (boxes + 1) / 2 * np.array([w - 1, h - 1, d - 1])  # voxel index units (x, y, z)
    points = np.array([grid.GetPoint(i) for i in range(grid.GetNumberOfPoints())]).reshape(count, 8, 3)
    order = [0, 1, 3, 2, 4, 5, 7, 6]  # VTK hexahedron corner order
    np.testing.assert_allclose(points, expected[:, order], rtol=1e-6, atol=1e-6)
    # Corners in VTK's order give every hexahedron a positive volume (a wrong order gives a negative or
    # degenerate one): the box's volume in index units, det(diag(extent) A^-1) / 8 * 8.
    for i in range(count):
        edges = expected[i, [1, 2, 4]] - expected[i, 0]  # [3, 3] edge vectors along local x, y, z
        assert vtk.vtkMeshQuality.HexVolume(grid.GetCell(i)) == pytest.approx(np.linalg.det(edges), rel=1e-4)
        assert np.linalg.det(edges) > 0


def test_animation_replays_training_and_ends_at_the_saved_grids(trained, tmp_path, capsys):
    path, data, model = trained
    prefix = tmp_path / "moving"
    assert main(["grids", str(model), str(path), "--out", str(prefix), "--animate", "--every", "5"]) == 0
    assert "(4 frames)" in capsys.readouterr().out  # iterations 0, 5, 10 and 12
    with Image.open(f"{prefix}.gif") as animation:
        assert animation.n_frames == 4

    field = apmgsrn.load(model)
    history = record_grid_history(field, ArrayVolume(data), 6, torch.device("cpu"))
    assert history.iterations == [0, 6, 12]
    # Same seed, same settings: the replay ends where the saved model's grids are; they moved on the way.
    np.testing.assert_allclose(history.boxes[-1], field.field.encoder.grid_boxes().numpy(), atol=1e-5)
    assert np.abs(history.boxes[-1] - history.boxes[0]).max() > 1e-4


def test_models_without_adaptive_grids_are_refused(trained, tmp_path, capsys):
    path, _, _ = trained
    model = tmp_path / "ngp.apmgsrn"
    assert main(["train", str(path), "--model", "ngp", "--out", str(model), "--iterations", "2",
                 "--batch-size", "256", "--device", "cpu"]) == 0
    capsys.readouterr()
    assert main(["grids", str(model), str(path), "--out", str(tmp_path / "x")]) == 2
    assert "ngp model without adaptive grids" in capsys.readouterr().err


def test_box_outline_is_the_convex_hull_of_the_projected_corners():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [0.2, 0.9], [1, 0.5]])
    hull = convex_hull(square)
    assert {tuple(p) for p in hull} == {(0, 0), (1, 0), (1, 1), (0, 1)}  # interior and edge points dropped
    points = np.random.default_rng(0).normal(size=(40, 2))
    hull = convex_hull(points)
    edges = np.roll(hull, -1, axis=0) - hull  # counter-clockwise: every point is left of every edge
    offsets = points[:, None, :] - hull[None]  # [40, H, 2]
    cross = edges[None, :, 0] * offsets[..., 1] - edges[None, :, 1] * offsets[..., 0]
    assert (cross >= -1e-12).all() and 3 <= len(hull) < 40
