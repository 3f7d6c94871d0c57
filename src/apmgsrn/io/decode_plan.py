"""What a decode of a model writes: which lattice, and the names, attributes, coordinates and compression
its source had (recorded in the model file at training time).

The plan is plain data; :func:`apmgsrn.inference.decode.decode_volume` (a file) and the notebook API (an
array) carry it out.
"""

from __future__ import annotations

from dataclasses import dataclass

from apmgsrn.data.grid import AXES, Region, SampleGrid, sample_grid
from apmgsrn.data.writers import OutputAxis
from apmgsrn.io.description import ModelDescription, check_time


@dataclass(frozen=True)
class DecodePlan:
    """A decode, ready to run.

    Attributes:
        grid: the lattice (a box of the training volume at a resolution).
        time: the time step.
        variable: the variable's name (the source's, else ``value``).
        variable_attributes: the source variable's attributes (``units``...).
        axes: the ``(z, y, x)`` axes: dimension names and the coordinates of every sample.
        compression: the source's compression (for a NetCDF output), or None.
        attributes: global attributes of a NetCDF output.
    """

    grid: SampleGrid
    time: int
    variable: str
    variable_attributes: dict
    axes: tuple[OutputAxis, OutputAxis, OutputAxis]
    compression: dict | None
    attributes: dict

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(D, H, W)`` samples."""
        return self.grid.shape

    @property
    def origin(self) -> tuple[float, float, float]:
        """``(x, y, z)`` of the first sample, in the source's coordinates (voxel indices where it had none)."""
        return tuple(float(axis.values[0]) for axis in reversed(self.axes))

    @property
    def spacing(self) -> tuple[float, float, float]:
        """``(x, y, z)`` distance between samples (the mean one on an uneven axis; 1 on a one-sample axis)."""
        return tuple(float((a.values[-1] - a.values[0]) / (len(a.values) - 1)) if len(a.values) > 1 else 1.0
                     for a in reversed(self.axes))

    def writer_options(self) -> dict:
        """Keyword arguments of :class:`~apmgsrn.data.writers.VolumeWriter`."""
        return dict(variable=self.variable, attributes=self.attributes, variable_attributes=self.variable_attributes,
                    axes=self.axes, compression=self.compression)


def plan_decode(
    description: ModelDescription,
    shape: tuple[int, int, int] | None = None,
    region: Region | None = None,
    time: int | None = None,
    attributes: dict | None = None,
) -> DecodePlan:
    """Plan a decode of a model.

    Args:
        description: the model's description.
        shape: ``(D, H, W)`` samples (default: the training volume's voxel spacing over the region).
        region: the box to decode (default: the whole volume).
        time: the time step (default: the first).
        attributes: global attributes of a NetCDF output.

    Raises:
        ApmgsrnError: a region outside the volume or empty, a bad shape, a time step the model lacks.
    """
    source = description.source
    metadata = source.metadata
    step = check_time(description, time)
    grid = sample_grid(description.volume_shape, shape, region, metadata)
    axes = []
    for axis in range(3):
        coordinates = metadata.axis(axis)
        recorded = metadata.coordinates is not None and metadata.coordinates[axis] is not None
        name = metadata.dimensions[axis] if metadata.dimensions is not None else coordinates.name or AXES[axis]
        axes.append(OutputAxis(name, coordinates.at(grid.indices(axis)), dict(coordinates.attributes), recorded))
    # A dataset path (HDF5 "fields/rho") is no NetCDF or VTK name: its last part is.
    variable = (source.variable or "value").rsplit("/", 1)[-1] or "value"
    return DecodePlan(grid, step, variable, dict(metadata.attributes), tuple(axes), metadata.compression,
                      dict(attributes or {}))
