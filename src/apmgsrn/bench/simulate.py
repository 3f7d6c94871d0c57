"""Benchmark volumes no compressor made: decaying incompressible turbulence from a small spectral solver.

The volumes of the comparisons with classical compressors must not come from a lossy compressor themselves
(a compressor re-encodes its own artefacts almost for free). This module makes such volumes here, with numpy
alone: a pseudo-spectral solver of the 3-D incompressible Navier-Stokes equations on the periodic cube
``[0, 2 pi)^3``,

    du/dt + (omega x u) + grad(P) = nu laplace(u),    div(u) = 0,    omega = curl(u),

(rotational form, ``P`` the total pressure), from random vortices: a divergence-free Gaussian velocity field
with energy spectrum ``E(k) ~ k^4 exp(-2 (k / k0)^2)``, scaled to unit RMS velocity per component. Time stepping:
Heun's second-order Runge-Kutta with an integrating factor for the viscous term; the nonlinear term is computed
in physical space and dealiased by the 2/3 rule; the pressure is the projection onto divergence-free fields.
The written fields are the vorticity magnitude ``|omega|`` (intermittent: thin tubes and sheets) and the
velocity's x component (smooth, large scales), float32, C order ``(z, y, x)``.

    python -m apmgsrn.bench.simulate --size 128 --out benchmarks/data

writes ``turbulence_vorticity_128.npy``, ``turbulence_velocity_x_128.npy`` and ``turbulence_128.txt`` (the
provenance: equations, parameters, seed, steps, energy, the command). A run is deterministic for a seed on one
machine (numpy's FFT; the last bits of float32 sums may differ across machines).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from apmgsrn.errors import ApmgsrnError


@dataclass(frozen=True)
class TurbulenceRun:
    """Parameters of one decaying-turbulence run.

    Attributes:
        size: grid points per axis (even).
        viscosity: kinematic viscosity ``nu`` (the RMS velocity starts at 1 and the box is ``2 pi`` wide).
        peak_wavenumber: ``k0``, where the initial energy spectrum peaks (vortices about ``2 pi / k0`` wide).
        time_step: ``dt``, fixed (the run refuses to go on once the CFL number passes :data:`MAX_CFL`).
        steps: time steps taken.
        seed: seed of numpy's default generator for the initial field.
    """

    size: int = 128
    viscosity: float = 1e-2
    peak_wavenumber: float = 4.0
    time_step: float = 0.005
    steps: int = 300
    seed: int = 0

    def __post_init__(self) -> None:
        if self.size < 8 or self.size % 2:
            raise ApmgsrnError(f"size {self.size}: must be even and at least 8")
        for name in ("viscosity", "peak_wavenumber", "time_step"):
            if not getattr(self, name) > 0:
                raise ApmgsrnError(f"{name} {getattr(self, name)!r}: must be positive")
        if self.steps < 0:
            raise ApmgsrnError(f"steps {self.steps}: must be 0 or more")


#: CFL number ``max|u| dt / dx`` above which explicit RK2 is no longer trusted.
MAX_CFL = 1.0

#: The runs behind the shipped and benchmark volumes (the provenance text records them in full).
BENCHMARK_RUN = TurbulenceRun()
TEST_RUN = TurbulenceRun(size=48, viscosity=1.5e-2, time_step=0.02, steps=60)


@dataclass(frozen=True)
class TurbulenceResult:
    """The fields at the end of a run, and its history."""

    vorticity: np.ndarray  # [N, N, N] float32, |omega|
    velocity_x: np.ndarray  # [N, N, N] float32, u_x
    energy: list[float]  # mean kinetic energy 0.5 <|u|^2> every tenth step, and at the end
    max_cfl: float
    seconds: float


class _Spectral:
    """Wavenumbers, dealiasing mask and transforms of an ``N^3`` periodic grid (real-to-complex, float32)."""

    def __init__(self, size: int):
        k = np.fft.fftfreq(size, 1.0 / size).astype(np.float32)
        kr = np.fft.rfftfreq(size, 1.0 / size).astype(np.float32)
        self.k = (k[:, None, None], k[None, :, None], kr[None, None, :])  # (z, y, x) components
        self.k2 = self.k[0] ** 2 + self.k[1] ** 2 + self.k[2] ** 2
        self.k2_safe = np.where(self.k2 == 0, 1.0, self.k2).astype(np.float32)
        cut = size / 3.0  # 2/3 rule: keep |k_i| < N/3 on every axis
        self.dealias = ((np.abs(self.k[0]) < cut) & (np.abs(self.k[1]) < cut) & (np.abs(self.k[2]) < cut))
        self.size = size

    def forward(self, field: np.ndarray) -> np.ndarray:
        return np.fft.rfftn(field, axes=(-3, -2, -1)).astype(np.complex64, copy=False)

    def inverse(self, spectrum: np.ndarray) -> np.ndarray:
        shape = (self.size,) * 3
        return np.fft.irfftn(spectrum, s=shape, axes=(-3, -2, -1)).astype(np.float32, copy=False)

    def project(self, spectrum: np.ndarray) -> np.ndarray:
        """The divergence-free part of a vector field's spectrum ``[3, ...]`` (components z, y, x)."""
        divergence = sum(k * s for k, s in zip(self.k, spectrum))
        return np.stack([s - k * divergence / self.k2_safe for k, s in zip(self.k, spectrum)])

    def curl(self, spectrum: np.ndarray) -> np.ndarray:
        """``i k x u``, components (z, y, x)."""
        kz, ky, kx = self.k
        uz, uy, ux = spectrum
        return 1j * np.stack([kx * uy - ky * ux, kz * ux - kx * uz, ky * uz - kz * uy])


def initial_velocity(run: TurbulenceRun, spectral: _Spectral) -> np.ndarray:
    """Random divergence-free velocity spectrum ``[3, N, N, N//2+1]`` with ``E(k) ~ k^4 exp(-2 (k/k0)^2)``."""
    rng = np.random.default_rng(run.seed)
    noise = rng.standard_normal((3,) + (run.size,) * 3, dtype=np.float32)
    spectrum = spectral.forward(noise)
    k = np.sqrt(spectral.k2)
    # White noise has the same energy in every mode, so a shell holds ~ k^2 of it: amplitude k exp(-(k/k0)^2)
    # gives E(k) ~ k^2 * k^2 exp(-2 (k/k0)^2).
    amplitude = (k / run.peak_wavenumber) * np.exp(-((k / run.peak_wavenumber) ** 2))
    spectrum = spectral.project(spectrum * amplitude * spectral.dealias)
    velocity = spectral.inverse(spectrum)
    rms = float(np.sqrt(np.mean(velocity.astype(np.float64) ** 2)))
    return (spectrum / rms).astype(np.complex64)


def _nonlinear(spectrum: np.ndarray, spectral: _Spectral) -> tuple[np.ndarray, float]:
    """``-P(omega x u)`` dealiased, and ``max |u|`` (for the CFL number)."""
    velocity = spectral.inverse(spectrum)
    vorticity = spectral.inverse(spectral.curl(spectrum))
    uz, uy, ux = velocity
    wz, wy, wx = vorticity
    # u x omega, components (z, y, x)
    cross = np.stack([ux * wy - uy * wx, uz * wx - ux * wz, uy * wz - uz * wy])
    speed = float(np.sqrt((velocity.astype(np.float64) ** 2).sum(axis=0)).max())
    return spectral.project(spectral.forward(cross) * spectral.dealias), speed


def simulate(run: TurbulenceRun, log=None) -> TurbulenceResult:
    """Integrate ``run`` and return the final vorticity magnitude and x velocity.

    Raises:
        ApmgsrnError: the CFL number passed :data:`MAX_CFL` (a smaller time step is needed).
    """
    start = time.perf_counter()
    spectral = _Spectral(run.size)
    spectrum = initial_velocity(run, spectral)
    factor = np.exp(-run.viscosity * spectral.k2 * run.time_step).astype(np.float32)
    dx = 2 * np.pi / run.size
    energy, max_cfl = [], 0.0
    for step in range(run.steps):
        if step % 10 == 0:
            energy.append(_energy(spectrum, spectral))
            if log is not None:
                log(f"step {step}/{run.steps}: energy {energy[-1]:.4f}, max CFL so far {max_cfl:.2f}")
        slope, speed = _nonlinear(spectrum, spectral)
        guess = factor * (spectrum + run.time_step * slope)
        slope2, _ = _nonlinear(guess, spectral)
        spectrum = (factor * (spectrum + 0.5 * run.time_step * slope) + 0.5 * run.time_step * slope2).astype(
            np.complex64)
        max_cfl = max(max_cfl, speed * run.time_step / dx)
        if max_cfl > MAX_CFL:
            raise ApmgsrnError(f"CFL number {max_cfl:.2f} at step {step}: above {MAX_CFL}; take a smaller time step")
    energy.append(_energy(spectrum, spectral))
    velocity = spectral.inverse(spectrum)
    vorticity = spectral.inverse(spectral.curl(spectrum))
    magnitude = np.sqrt((vorticity.astype(np.float64) ** 2).sum(axis=0)).astype(np.float32)
    return TurbulenceResult(magnitude, np.ascontiguousarray(velocity[2]), energy, max_cfl,
                            time.perf_counter() - start)


def _energy(spectrum: np.ndarray, spectral: _Spectral) -> float:
    velocity = spectral.inverse(spectrum).astype(np.float64)
    return float(0.5 * (velocity**2).sum(axis=0).mean())


def provenance_text(run: TurbulenceRun, result: TurbulenceResult, command: str, files: list[str]) -> str:
    """What a volume is and how to make it again."""
    lines = [
        f"Decaying incompressible turbulence, {run.size}^3, made by apmgsrn.bench.simulate (no compressor involved).",
        "",
        "Equations: du/dt + omega x u + grad P = nu laplace u, div u = 0, omega = curl u, periodic cube [0, 2 pi)^3.",
        "Method: pseudo-spectral (numpy FFT, float32), 2/3-rule dealiasing, projection for the pressure, Heun RK2",
        "with an integrating factor exp(-nu k^2 dt) for the viscous term.",
        "Initial field: divergence-free Gaussian velocity, E(k) ~ k^4 exp(-2 (k/k0)^2), RMS velocity 1 per component,",
        "from numpy.random.default_rng(seed).standard_normal.",
        "",
        "Parameters: " + ", ".join(f"{key}={value}" for key, value in asdict(run).items()),
        f"Final time: {run.steps * run.time_step:g}; largest CFL number: {result.max_cfl:.3f};"
        f" kinetic energy (every tenth step, then the end): {', '.join(f'{e:.4f}' for e in result.energy)}.",
        f"Run time: {result.seconds:.0f} s on {_threads_text()}.",
        "",
        "Files (float32, C order (z, y, x), x fastest):",
    ]
    describe = {"vorticity": "vorticity magnitude |omega| at the final time",
                "velocity_x": "x component of the velocity at the final time"}
    for name in files:
        key = "vorticity" if "vorticity" in name else "velocity_x"
        lines.append(f"  {name}: {describe[key]}")
    lines += ["", f"Regenerate: {command}", ""]
    return "\n".join(lines)


def _threads_text() -> str:
    import os

    return f"{os.cpu_count()} CPU core(s) visible"


def write_run(run: TurbulenceRun, out: Path, log=print) -> list[Path]:
    """Simulate ``run`` and write ``turbulence_{vorticity,velocity_x}_N.npy`` and ``turbulence_N.txt`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    result = simulate(run, log=log)
    names = [f"turbulence_vorticity_{run.size}.npy", f"turbulence_velocity_x_{run.size}.npy"]
    np.save(out / names[0], result.vorticity)
    np.save(out / names[1], result.velocity_x)
    command = (f"python -m apmgsrn.bench.simulate --size {run.size} --viscosity {run.viscosity:g} "
               f"--peak-wavenumber {run.peak_wavenumber:g} --time-step {run.time_step:g} --steps {run.steps} "
               f"--seed {run.seed} --out {out}")
    text = provenance_text(run, result, command, names)
    (out / f"turbulence_{run.size}.txt").write_text(text)
    return [out / name for name in names] + [out / f"turbulence_{run.size}.txt"]


def main(argv: list[str] | None = None) -> int:
    defaults = BENCHMARK_RUN
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=defaults.size)
    parser.add_argument("--viscosity", type=float, default=defaults.viscosity)
    parser.add_argument("--peak-wavenumber", type=float, default=defaults.peak_wavenumber)
    parser.add_argument("--time-step", type=float, default=defaults.time_step)
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--out", type=Path, required=True, help="folder for the .npy volumes and the provenance")
    args = parser.parse_args(argv)
    try:
        run = TurbulenceRun(args.size, args.viscosity, args.peak_wavenumber, args.time_step, args.steps, args.seed)
        for path in write_run(run, args.out):
            print(path)
    except ApmgsrnError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
