"""Benchmark data no compressor made: the turbulence solver, and the registry of benchmark volumes."""

from pathlib import Path

import numpy as np
import pytest

from apmgsrn.bench import datasets
from apmgsrn.bench.simulate import TEST_RUN, TurbulenceRun, _Spectral, initial_velocity, main, simulate
from apmgsrn.errors import ApmgsrnError

TINY = TurbulenceRun(size=16, viscosity=0.05, time_step=0.02, steps=12, seed=3)


def test_the_initial_field_is_divergence_free_with_unit_rms_velocity():
    spectral = _Spectral(TINY.size)
    spectrum = initial_velocity(TINY, spectral)
    divergence = sum(k * s for k, s in zip(spectral.k, spectrum))
    assert float(np.abs(divergence).max()) <= 1e-4 * float(np.abs(spectrum).max())
    velocity = spectral.inverse(spectrum).astype(np.float64)
    assert np.sqrt(np.mean(velocity**2)) == pytest.approx(1.0, rel=1e-4)


def test_decaying_turbulence_loses_energy_and_is_the_same_for_the_same_seed():
    first, again = simulate(TINY), simulate(TINY)
    assert first.vorticity.shape == first.velocity_x.shape == (16, 16, 16)
    assert first.vorticity.dtype == first.velocity_x.dtype == np.float32
    assert float(first.vorticity.min()) >= 0
    # No forcing: viscosity only removes energy.
    assert all(later < earlier for earlier, later in zip(first.energy, first.energy[1:]))
    assert np.array_equal(first.vorticity, again.vorticity)
    other = simulate(TurbulenceRun(**{**TINY.__dict__, "seed": 4}))
    assert not np.array_equal(first.vorticity, other.vorticity)


def test_a_time_step_past_the_cfl_limit_is_refused():
    with pytest.raises(ApmgsrnError, match="CFL number .* take a smaller time step"):
        simulate(TurbulenceRun(size=16, time_step=1.0, steps=3))


@pytest.mark.parametrize("field, value", [("size", 7), ("size", 4), ("viscosity", 0.0), ("time_step", -1.0),
                                          ("steps", -1)])
def test_bad_run_parameters_are_refused(field, value):
    with pytest.raises(ApmgsrnError, match=field):
        TurbulenceRun(**{field: value})


def test_the_command_writes_the_volumes_and_a_provenance_that_regenerates_them(tmp_path, capsys):
    out = tmp_path / "turbulence"
    assert main(["--size", "16", "--viscosity", "0.05", "--time-step", "0.02", "--steps", "12", "--seed", "3",
                 "--out", str(out)]) == 0
    vorticity = np.load(out / "turbulence_vorticity_16.npy")
    assert np.array_equal(vorticity, simulate(TINY).vorticity)
    assert np.load(out / "turbulence_velocity_x_16.npy").shape == (16, 16, 16)
    text = (out / "turbulence_16.txt").read_text()
    assert "du/dt + omega x u + grad P = nu laplace u" in text
    assert "size=16, viscosity=0.05, peak_wavenumber=4.0, time_step=0.02, steps=12, seed=3" in text
    assert f"Regenerate: python -m apmgsrn.bench.simulate --size 16 --viscosity 0.05 --peak-wavenumber 4 " \
           f"--time-step 0.02 --steps 12 --seed 3 --out {out}" in text
    assert main(["--size", "9", "--out", str(out)]) == 2
    assert "error: size 9: must be even" in capsys.readouterr().err


def test_the_bundled_test_volume_is_the_test_run(test_data):
    volume = np.load(test_data / "turbulence_vorticity_48.npy")
    assert volume.shape == (TEST_RUN.size,) * 3 and volume.dtype == np.float32
    assert float(volume.min()) >= 0 and np.isfinite(volume).all()


def test_the_registry_marks_exactly_the_zfp_previews_and_keeps_them_out_of_the_classical_comparisons():
    names = [volume.name for volume in datasets.BENCHMARK_VOLUMES]
    assert len(names) == len(set(names))
    previews = {v.file for v in datasets.BENCHMARK_VOLUMES if v.compressed is not None}
    assert previews == {"miranda_density_256.nc", "hcci_oh_187.nc", "channel_pressure_640x240x48.nc"}
    assert all(v.compressed == "decoded from ZFP previews: for SRN comparisons only"
               for v in datasets.BENCHMARK_VOLUMES if v.compressed is not None)
    classical = datasets.classical_comparison_volumes()
    assert not {v.file for v in classical} & previews
    steps = [v for v in classical if v.file.startswith("viscous_fingers_run01/")]
    assert len(steps) == 30
    assert all(v.make and "apmgsrn.bench.simulate" in v.make for v in classical if v.root == "generated")


def test_every_registered_shared_file_is_in_the_shared_data():
    if not datasets.SHARED_DATA.is_dir():
        pytest.skip(f"no shared data at {datasets.SHARED_DATA}")
    missing = [v.file for v in datasets.BENCHMARK_VOLUMES if v.root == "shared" and not v.path().exists()]
    assert missing == []


def test_a_registered_name_is_a_data_spec_and_a_missing_generated_file_says_how_to_make_it(tmp_path, monkeypatch):
    present = datasets.BenchmarkVolume("here", "v.npy", None, "generated", "test")
    absent = datasets.BenchmarkVolume("gone", "w.npy", None, "generated", "test", make="python -m make-it")
    np.save(tmp_path / "v.npy", np.zeros((2, 2, 2), np.float32))
    monkeypatch.setattr(datasets, "BENCHMARK_VOLUMES", (present, absent))
    monkeypatch.setattr(datasets.BenchmarkVolume, "path", lambda self, *a: tmp_path / self.file)
    assert datasets.parse_data_spec("here").path == tmp_path / "v.npy"
    with pytest.raises(ApmgsrnError, match="gone: the registered volume's file .* is missing; make it with python -m"):
        datasets.parse_data_spec("gone")
    with pytest.raises(ApmgsrnError, match="no such volume file"):
        datasets.parse_data_spec(str(Path("nowhere") / "x.npy"))
