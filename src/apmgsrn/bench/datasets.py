"""Naming the volumes of a benchmark on the command line: ``PATH[:VARIABLE]``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from apmgsrn.errors import ApmgsrnError


@dataclass(frozen=True)
class DataSpec:
    """One benchmark volume.

    Attributes:
        path: the file (or Zarr directory).
        variable: variable / dataset / array name, or None for the only 3-D one.
    """

    path: Path
    variable: str | None = None

    @property
    def label(self) -> str:
        """Short name used in tables: ``file.nc:variable`` (or just the file name)."""
        return self.path.name + (f":{self.variable}" if self.variable else "")

    @property
    def stem(self) -> str:
        """File-name-safe label, for the model files a benchmark writes."""
        text = self.path.name.split(".")[0] + (f"-{self.variable}" if self.variable else "")
        return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in text)


def parse_data_spec(text: str) -> DataSpec:
    """``"PATH"`` or ``"PATH:VARIABLE"`` -> :class:`DataSpec` (a path that exists as typed wins).

    Raises:
        ApmgsrnError: neither the path nor the part before the last ``:`` exists.
    """
    path = Path(text)
    if path.exists():
        return DataSpec(path)
    head, sep, variable = text.rpartition(":")
    if sep and head and variable and Path(head).exists():
        return DataSpec(Path(head), variable)
    raise ApmgsrnError(f"{text}: no such volume file; give PATH or PATH:VARIABLE of an existing file")


def open_spec(spec: DataSpec, fill_nonfinite: float | None = None):
    """Open the volume of ``spec`` lazily (raw files take their dims and type from the file name)."""
    # Imported here: the CLI imports this module to parse arguments, and --help loads no numpy.
    from apmgsrn.data import open_volume

    return open_volume(spec.path, variable=spec.variable, fill_nonfinite=fill_nonfinite)
