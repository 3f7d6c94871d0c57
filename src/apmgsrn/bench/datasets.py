"""Benchmark volumes: naming one on the command line (``PATH[:VARIABLE]``), and the registered volumes.

The registry (:data:`BENCHMARK_VOLUMES`) says of each volume whether a lossy compressor produced it: the NetCDF
files of the shared data were decoded from ZFP previews and serve the SRN comparisons only; the comparisons
with classical compressors use the others (:func:`classical_comparison_volumes`), among them the turbulence
that :mod:`apmgsrn.bench.simulate` computes here.
"""

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
    """``"PATH"``, ``"PATH:VARIABLE"`` or the name of a registered volume whose file is here
    (:data:`BENCHMARK_VOLUMES`) -> :class:`DataSpec` (a path that exists as typed wins).

    Raises:
        ApmgsrnError: neither the path nor the part before the last ``:`` exists, nor a registered volume's file.
    """
    path = Path(text)
    if path.exists():
        return DataSpec(path)
    head, sep, variable = text.rpartition(":")
    if sep and head and variable and Path(head).exists():
        return DataSpec(Path(head), variable)
    registered = next((volume for volume in BENCHMARK_VOLUMES if volume.name == text), None)
    if registered is not None:
        if registered.path().exists():
            return registered.spec()
        how = f"make it with {registered.make}" if registered.make else f"it belongs in {SHARED_DATA}"
        raise ApmgsrnError(f"{text}: the registered volume's file {registered.path()} is missing; {how}")
    raise ApmgsrnError(f"{text}: no such volume file; give PATH or PATH:VARIABLE of an existing file")


def open_spec(spec: DataSpec, fill_nonfinite: float | None = None):
    """Open the volume of ``spec`` lazily (raw files take their dims and type from the file name)."""
    # Imported here: the CLI imports this module to parse arguments, and --help loads no numpy.
    from apmgsrn.data import open_volume

    return open_volume(spec.path, variable=spec.variable, fill_nonfinite=fill_nonfinite)


#: Where the registered volumes lie in a checkout: the project's shared sample data beside it, and the folder
#: the solver of :mod:`apmgsrn.bench.simulate` writes to (made on demand, not committed).
CHECKOUT = Path(__file__).resolve().parents[3]
SHARED_DATA = CHECKOUT.parent / "shared" / "data"
GENERATED_DATA = CHECKOUT / ".bench_data" / "turbulence"

#: What a volume decoded from a lossy compressor's output is good for: ZFP restores its own previews almost
#: exactly, so the classical comparisons would favour it.
ZFP_PREVIEW = "decoded from ZFP previews: for SRN comparisons only"


@dataclass(frozen=True)
class BenchmarkVolume:
    """One registered benchmark volume.

    Attributes:
        name: short name for tables and command lines.
        file: path under its root.
        variable: variable / array name, or None for the only one.
        root: ``"shared"`` (:data:`SHARED_DATA`) or ``"generated"`` (:data:`GENERATED_DATA`).
        what: what the values are, dims x*y*z, where they come from.
        compressed: None when no lossy compressor produced the values; else what that means for their use
            (:data:`ZFP_PREVIEW`).
        make: the command that writes a generated volume.
    """

    name: str
    file: str
    variable: str | None
    root: str
    what: str
    compressed: str | None = None
    make: str | None = None

    def path(self, shared: Path = SHARED_DATA, generated: Path = GENERATED_DATA) -> Path:
        return (shared if self.root == "shared" else generated) / self.file

    def spec(self, shared: Path = SHARED_DATA, generated: Path = GENERATED_DATA) -> DataSpec:
        """The :class:`DataSpec` of this volume under the given roots."""
        return DataSpec(self.path(shared, generated), self.variable)


_MAKE_TURBULENCE = "python -m apmgsrn.bench.simulate --size 128 --out .bench_data/turbulence"
_VISCOUS_FINGERS = ("salt concentration in viscous fingering (SciVis contest 2016, run01), 64^3; "
                    "topology-tool-kit/ttk-data")

BENCHMARK_VOLUMES: tuple[BenchmarkVolume, ...] = (
    BenchmarkVolume("turbulence-vorticity-128", "turbulence_vorticity_128.npy", None, "generated",
                    "vorticity magnitude of decaying incompressible turbulence, 128^3 float32 "
                    "(apmgsrn.bench.simulate; provenance in turbulence_128.txt)", make=_MAKE_TURBULENCE),
    BenchmarkVolume("turbulence-velocity-x-128", "turbulence_velocity_x_128.npy", None, "generated",
                    "x velocity of the same run, 128^3 float32", make=_MAKE_TURBULENCE),
    BenchmarkVolume("richtmyer-meshkov", "richtmyer_meshkov_t20_256x256x256_uint8.raw", None, "shared",
                    "Richtmyer-Meshkov instability (LLNL), 256^3 uint8 (quantised, not compressed); fV-SRN"),
    BenchmarkVolume("c60", "c60_128x128x128_uint8.raw", None, "shared", "C60 molecule field, 128^3 uint8; DiffDVR"),
    BenchmarkVolume("cth-pressure", "cth_armor_penetration.vtr", "Pressure", "shared",
                    "CTH armor penetration pressure, 128x64x64 cells float32; pyvista/vtk-data"),
    BenchmarkVolume("neghip", "neghip_64x64x64_uint8.raw", None, "shared", "protein electron probability, 64^3 uint8"),
    BenchmarkVolume("darkmatter", "darkmatter_density_64.h5", "densityfield", "shared",
                    "dark-matter density (DTFE of a GADGET-4 run), 64^3 float32"),
    *(BenchmarkVolume(f"viscous-fingers-t{step:03d}", f"viscous_fingers_t{step:03d}.vti", None, "shared",
                      f"{_VISCOUS_FINGERS}, step {step}") for step in (10, 50, 90)),
    *(BenchmarkVolume(f"viscous-fingers-run01-{step:03d}",
                      f"viscous_fingers_run01/{step:03d}_density_{step:03d}_064_2.0.vti", None, "shared",
                      f"{_VISCOUS_FINGERS}, step {step} of the 30-step series") for step in range(30, 60)),
    BenchmarkVolume("miranda", "miranda_density_256.nc", "density", "shared",
                    "Rayleigh-Taylor mixing density, 256^3 float32; open-scivis-datasets preview", ZFP_PREVIEW),
    BenchmarkVolume("hcci", "hcci_oh_187.nc", "oh", "shared",
                    "combustion DNS, OH, 187^3 float32; open-scivis-datasets preview", ZFP_PREVIEW),
    BenchmarkVolume("channel", "channel_pressure_640x240x48.nc", "pressure", "shared",
                    "turbulent channel flow pressure, 640x240x48 float32; open-scivis-datasets preview", ZFP_PREVIEW),
)


def benchmark_volume(name: str) -> BenchmarkVolume:
    """The registered volume called ``name``.

    Raises:
        ApmgsrnError: no such volume.
    """
    for volume in BENCHMARK_VOLUMES:
        if volume.name == name:
            return volume
    raise ApmgsrnError(f"unknown benchmark volume {name!r}; choose from "
                       f"{', '.join(v.name for v in BENCHMARK_VOLUMES)}")


def classical_comparison_volumes() -> tuple[BenchmarkVolume, ...]:
    """The volumes no lossy compressor produced: the ones to measure classical compressors on."""
    return tuple(volume for volume in BENCHMARK_VOLUMES if volume.compressed is None)
