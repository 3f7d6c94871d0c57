"""What the adaptive grids learned: boxes over maximum-intensity projections, a VTK file, an animation.

- :func:`grid_picture`: three panels, the volume's maximum-intensity projection (MIP) along z, y and x with
  the outline of every grid box projected on it.
- :func:`write_grid_vtk`: the boxes as hexahedra in a legacy VTK file that ParaView opens beside the volume
  (in voxel-index coordinates by default, where ParaView shows a volume that has no spacing of its own).
- :func:`record_grid_history` and :func:`write_grid_animation`: train the model again with its recorded
  settings (same seed, so the same run) through the fitting pipeline, a :class:`GridRecorder` callback
  keeping the grid maps every K iterations, and draw them as a GIF.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from apmgsrn.arguments import check_int, check_optional_int
from apmgsrn.atomic import atomic_write, atomic_write_text
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.evaluate import check_volume_shape
from apmgsrn.models.field import NeuralField
from apmgsrn.recipes import RUNTIME
from apmgsrn.training.callbacks import TrainingProgress
from apmgsrn.training.fit import prepare_values, train_prepared
from apmgsrn.training.trainer import StepLosses, TrainConfig, Trainer, TrainingCallback

# Panel -> (projected-out axis index in (z, y, x) array order, horizontal and vertical point coordinate).
_PANELS = (("along z", 0, 0, 1), ("along y", 1, 0, 2), ("along x", 2, 1, 2))
_AXIS_NAMES = "xyz"


@dataclass(frozen=True)
class Projections:
    """Maximum-intensity projections of a volume ``[D, H, W]``: along z ``[H, W]``, y ``[D, W]``, x ``[D, H]``."""

    along_z: np.ndarray
    along_y: np.ndarray
    along_x: np.ndarray

    def panel(self, axis: int) -> np.ndarray:
        return (self.along_z, self.along_y, self.along_x)[axis]


def require_grids(field, path: Path | str = "model") -> torch.Tensor:
    """Corners ``[M, 8, 3]`` (x, y, z) of the field's grid boxes.

    Raises:
        ApmgsrnError: the model has no adaptive grids (fvsrn, ngp or a brick model).
    """
    boxes = field.encoder.grid_boxes() if isinstance(field, NeuralField) else None
    if boxes is None:
        kind = field.config.model if isinstance(field, NeuralField) else "brick"
        raise ApmgsrnError(f"{path}: is a {kind} model without adaptive grids; pass an apmgsrn model")
    return boxes


def projections(volume, transform=None, slab_voxels: int = RUNTIME.slab_voxels) -> Projections:
    """MIPs along the three axes, streamed over z-slabs (one slab in memory at a time).

    Args:
        volume: a :class:`apmgsrn.data.Volume`.
        transform: optional value transform applied to the projections (monotonic, so it commutes with
            the maximum): pictures of log-scaled data show what the network fitted.
        slab_voxels: voxels per slab read at a time.
    """
    along_z = None
    along_y, along_x = [], []
    for _z, block in volume.iter_slabs(slab_voxels):
        top = block.max(axis=0)  # [H, W]
        along_z = top if along_z is None else np.maximum(along_z, top)
        along_y.append(block.max(axis=1))  # [dz, W]
        along_x.append(block.max(axis=2))  # [dz, H]
    result = [along_z, np.concatenate(along_y), np.concatenate(along_x)]
    if transform is not None:
        result = [transform.apply(np.asarray(r, dtype=np.float32)) for r in result]
    return Projections(*result)


def grid_picture(
    boxes: torch.Tensor | np.ndarray,
    mips: Projections,
    path: Path | None = None,
    title: str = "",
    figure=None,
):
    """Draw the grid boxes over the three MIPs; write a PNG when ``path`` is given.

    Args:
        boxes: ``[M, 8, 3]`` box corners (x, y, z) in ``[-1, 1]`` coordinates.
        mips: the volume's projections.
        path: PNG to write (None: only return the figure).
        title: figure title.
        figure: a matplotlib figure to draw into (reused by the animation).

    Returns:
        The matplotlib figure.
    """
    from matplotlib import colormaps

    if figure is None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        figure = Figure(figsize=(12, 4.3), dpi=100, layout="constrained")
        FigureCanvasAgg(figure)
    figure.clear()
    corners = np.asarray(boxes, dtype=np.float64)  # [M, 8, 3]
    colours = colormaps["tab20"](np.linspace(0, 1, max(len(corners), 2), endpoint=False))
    axes = figure.subplots(1, 3)
    for axis, (name, dropped, u, v) in zip(axes, _PANELS):
        image = mips.panel(dropped)
        axis.imshow(image, cmap="gray", origin="lower", extent=(-1, 1, -1, 1), interpolation="nearest")
        for m, box in enumerate(corners):
            # A box projects to a convex polygon: its outline is the hull of the 8 projected corners (the
            # inner edges would only clutter the picture).
            outline = convex_hull(box[:, [u, v]])
            closed = np.vstack([outline, outline[:1]])
            colour = colours[m % len(colours)]
            axis.plot(closed[:, 0], closed[:, 1], color=colour, linewidth=1.1, alpha=0.95)
        axis.set_xlim(-1.35, 1.35)
        axis.set_ylim(-1.35, 1.35)
        axis.set_aspect("equal")
        axis.set_title(f"MIP {name}")
        axis.set_xlabel(_AXIS_NAMES[u])
        axis.set_ylabel(_AXIS_NAMES[v])
    if title:
        figure.suptitle(title)
    if path is not None:
        atomic_write(path, figure.savefig, "picture")
    return figure


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of 2-D ``points`` ``[K, 2]``, counter-clockwise (monotone chain)."""
    ordered = sorted(map(tuple, np.asarray(points, dtype=np.float64)))

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def half(sequence):
        chain: list[tuple[float, float]] = []
        for p in sequence:
            while len(chain) >= 2 and cross(chain[-2], chain[-1], p) <= 0:
                chain.pop()
            chain.append(p)
        return chain

    lower, upper = half(ordered), half(reversed(ordered))
    return np.array(lower[:-1] + upper[:-1])


def write_grid_vtk(
    boxes: torch.Tensor | np.ndarray,
    path: Path,
    volume_shape: tuple[int, int, int] | None = None,
) -> None:
    """Write the grid boxes as a legacy ASCII VTK unstructured grid of hexahedra (cell data: grid index).

    Args:
        boxes: ``[M, 8, 3]`` corners (x, y, z) in ``[-1, 1]`` coordinates.
        path: ``.vtk`` file to write.
        volume_shape: ``(D, H, W)``: write voxel-index coordinates (``(p + 1) / 2 * (n - 1)``), which
            line up with the volume in ParaView; None keeps ``[-1, 1]`` coordinates.
    """
    corners = np.asarray(boxes, dtype=np.float64).copy()  # [M, 8, 3]
    if volume_shape is not None:
        d, h, w = volume_shape
        extent = np.array([w - 1, h - 1, d - 1], dtype=np.float64)  # (x, y, z)
        corners = (corners + 1) * 0.5 * extent
    m = corners.shape[0]
    lines = ["# vtk DataFile Version 3.0", "apmgsrn grid boxes", "ASCII", "DATASET UNSTRUCTURED_GRID"]
    lines.append(f"POINTS {8 * m} double")
    for box in corners:
        for k in (0, 1, 3, 2, 4, 5, 7, 6):  # VTK_HEXAHEDRON: the bottom face counter-clockwise, then the top
            lines.append(" ".join(f"{c:.9g}" for c in box[k]))
    lines.append(f"CELLS {m} {9 * m}")
    for i in range(m):
        lines.append("8 " + " ".join(str(8 * i + k) for k in range(8)))
    lines.append(f"CELL_TYPES {m}")
    lines += ["12"] * m  # VTK_HEXAHEDRON
    lines += [f"CELL_DATA {m}", "SCALARS grid int 1", "LOOKUP_TABLE default"]
    lines += [str(i) for i in range(m)]
    atomic_write_text(path, "\n".join(lines) + "\n", "VTK file")


@dataclass(frozen=True)
class GridHistory:
    """Grid boxes recorded during training: ``boxes[k]`` ``[M, 8, 3]`` after ``iterations[k]`` iterations."""

    iterations: list[int]
    boxes: list[np.ndarray]


def record_grid_history(
    model,
    volume,
    every: int,
    device: torch.device,
    iterations: int | None = None,
    log: Callable[[str], None] | None = None,
) -> GridHistory:
    """Train the model of ``field`` again, with the settings its file recorded, keeping the grids every ``every``.

    The training record of the model file holds the whole training configuration and seed, so this
    repeats the run that made the model (up to floating-point non-determinism of parallel reductions).

    Args:
        model: a loaded apmgsrn model (:func:`apmgsrn.load`; its training summary must hold the config).
        volume: the volume it was trained on.
        every: record the grids every this many iterations (and at 0 and the end).
        device: training device.
        iterations: train this many iterations instead of the recorded budget (shorter animation).
        log: receives a line when training starts.

    Raises:
        ApmgsrnError: the file holds no training record, the volume has another shape, or ``every`` or
            ``iterations`` is not a positive integer.
    """
    check_int("every", every, 1)
    check_optional_int("iterations", iterations, 1)
    field = model.field
    require_grids(field)
    recorded = model.description.training.get("config")
    if not recorded:
        raise ApmgsrnError("model file holds no training settings; animate a model written by 'apmgsrn train'")
    check_volume_shape(volume.shape, model.description.volume_shape, str(volume.path))
    settings = dict(recorded)
    settings["betas"] = tuple(settings.get("betas", (0.9, 0.99)))
    if iterations is not None:
        # A shorter run keeps the same shape of schedule: budget-relative defaults are recomputed.
        settings.update(iterations=int(iterations), density_start=None, history_every=None)
    config = TrainConfig(**{k: v for k, v in settings.items() if k in TrainConfig.__dataclass_fields__})
    transform = field.transform
    prepared = prepare_values(volume.to_numpy(), transform.kind, transform.offset, str(volume.path), device)
    if prepared.constant:
        raise ApmgsrnError(f"{volume.path}: every voxel has the same value, so the grids never move; nothing to show")
    recorder = GridRecorder(every)
    if log is not None:
        log(f"retraining {config.iterations} iterations to record the grids every {every}")
    train_prepared(prepared, field.config, config, volume.shape, callbacks=[recorder, TrainingProgress("replay")])
    return recorder.history


class GridRecorder(TrainingCallback):
    """Keeps the grid boxes at the start, every ``every`` iterations and at the end of the budget.

    Args:
        every: iterations between recorded states.
    """

    def __init__(self, every: int):
        self.every = check_int("every", every, 1)
        self.history = GridHistory([], [])

    def _record(self, trainer: Trainer, iteration: int) -> None:
        self.history.iterations.append(iteration)
        self.history.boxes.append(trainer.field.encoder.grid_boxes().detach().cpu().numpy())  # [M, 8, 3]

    def on_start(self, trainer: Trainer) -> None:
        self._record(trainer, trainer.state.iteration)

    def after_step(self, trainer: Trainer, iteration: int, losses: StepLosses) -> None:
        if iteration % self.every == 0 or iteration == trainer.config.iterations:
            self._record(trainer, iteration)


def write_grid_animation(
    history: GridHistory,
    mips: Projections,
    path: Path,
    title: str = "",
    frame_ms: int = 150,
) -> int:
    """Draw every recorded state of the grids over the MIPs into an animated GIF.

    Args:
        history: recorded boxes.
        mips: the volume's projections.
        path: ``.gif`` file to write.
        title: prefix of each frame's title (the iteration follows).
        frame_ms: display time of a frame; the last frame stays three times as long.

    Returns:
        The number of frames.
    """
    from PIL import Image

    figure = None
    frames = []
    for iteration, boxes in zip(history.iterations, history.boxes):
        figure = grid_picture(boxes, mips, None, f"{title} iteration {iteration}".strip(), figure)
        figure.canvas.draw()
        rgba = np.asarray(figure.canvas.buffer_rgba())  # [height, width, 4]
        frames.append(Image.fromarray(rgba[..., :3].copy()).quantize(colors=128))
    durations = [frame_ms] * len(frames)
    durations[-1] = 3 * frame_ms
    atomic_write(path, lambda temp: frames[0].save(temp, save_all=True, append_images=frames[1:],
                                                   duration=durations, loop=0), "animation")
    return len(frames)
