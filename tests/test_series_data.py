"""Time series as inputs: several files, a glob, a time dimension, a .pvd collection; ordering, gaps and steps
that disagree (issue 16). Real data: the four consecutive viscous-fingering steps in tests/data."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from apmgsrn.data import open_volume
from apmgsrn.series.data import TimeSelection, is_series_input, open_series, order_by_step_number, parse_time
from apmgsrn.data.writers import VolumeWriter
from apmgsrn.errors import ApmgsrnError

STEPS = ["030", "031", "032", "033"]


@pytest.fixture(scope="module")
def run_folder(test_data) -> Path:
    return test_data / "viscous_fingers_run01"


@pytest.fixture(scope="module")
def step_files(run_folder) -> list[Path]:
    return [run_folder / f"{n}_density_{n}_064_2.0.vti" for n in STEPS]


@pytest.fixture(scope="module")
def truth(step_files) -> np.ndarray:
    return np.stack([open_volume(f).to_numpy() for f in step_files])  # [4, 32, 32, 32]


def test_glob_and_list_give_the_steps_in_number_order(run_folder, step_files, truth):
    by_glob = open_series(str(run_folder / "*.vti"))
    by_list = open_series([str(f) for f in reversed(step_files)])  # any order in, step order out
    for series in (by_glob, by_list):
        assert len(series) == 4
        assert series.labels == (30, 31, 32, 33)
        assert series.shape == (32, 32, 32) and series.variable == "ImageFile"
        np.testing.assert_array_equal(series.to_numpy(), truth)
    assert by_glob.raw_bytes == 4 * 32**3 * 4
    assert "4 steps 030_density_030_064_2.0.vti .. 033_density_033_064_2.0.vti:ImageFile 32x32x32" in by_glob.describe()


def test_the_step_number_is_the_number_that_differs():
    # 030_density_030_064_2.0: the step appears twice, the resolution 064 and the 2.0 never change.
    names = [Path(f"{n}_density_{n}_064_2.0.vti") for n in ("034", "030", "032")]
    assert [(n, p.name) for n, p in order_by_step_number(names)] == [
        (30, "030_density_030_064_2.0.vti"), (32, "032_density_032_064_2.0.vti"), (34, "034_density_034_064_2.0.vti")]
    with pytest.raises(ApmgsrnError, match=r"038_density_038_064_2.0.vti: step 38 follows step 34 .*step 36 is missing"):
        order_by_step_number(names + [Path("038_density_038_064_2.0.vti")])
    # A stride of 10 is a series, not a gap.
    ten = [Path(f"run_{n:04d}.h5") for n in (20, 0, 10, 30)]
    assert [n for n, _ in order_by_step_number(ten)] == [0, 10, 20, 30]


def test_a_gap_names_the_missing_step(step_files):
    with pytest.raises(ApmgsrnError) as caught:
        open_series([step_files[0], step_files[2], step_files[3]])
    message = str(caught.value)
    assert "032_density_032_064_2.0.vti" in message and "step 31 is missing" in message
    assert "\n" not in message


def test_names_without_a_distinguishing_number_are_refused(tmp_path, step_files):
    a, b = tmp_path / "first.vti", tmp_path / "second.vti"
    shutil.copy(step_files[0], a)
    shutil.copy(step_files[1], b)
    with pytest.raises(ApmgsrnError, match="carry no step number"):
        open_series([a, b])
    c = _copy(step_files[0], tmp_path / "run_1_b2.vti")
    with pytest.raises(ApmgsrnError, match="holds 1 number"):
        open_series([c, _copy(step_files[1], tmp_path / "run_2.vti")])


def _copy(source: Path, target: Path) -> Path:
    shutil.copy(source, target)
    return target


def test_duplicate_step_numbers_are_refused(tmp_path, step_files):
    _copy(step_files[0], tmp_path / "a_30.vti")
    _copy(step_files[1], tmp_path / "b_30.vti")
    _copy(step_files[2], tmp_path / "c_31.vti")
    # "a"/"b"/"c" are not numbers: the varying number is the step, and 30 appears twice.
    with pytest.raises(ApmgsrnError, match="step number 30"):
        open_series(str(tmp_path / "*.vti"))


def test_a_pattern_matching_nothing_is_an_error(tmp_path):
    with pytest.raises(ApmgsrnError, match="no file matches"):
        open_series(str(tmp_path / "*.vti"))


def test_steps_that_disagree_are_named_when_read(tmp_path, step_files, test_data):
    # Step 32 replaced by another real volume (the 32^3 neghip crop): another shape, dtype and variable.
    for n, source in zip(STEPS, step_files):
        _copy(source, tmp_path / f"step_{n}.vti")
    (tmp_path / "step_032.vti").unlink()
    np.save(tmp_path / "step_032.npy", np.load(test_data / "neghip_32x32x32_uint8.npy"))
    series = open_series([tmp_path / f"step_{n}.{'npy' if n == '032' else 'vti'}" for n in STEPS])
    series.read(1)  # the good steps read
    with pytest.raises(ApmgsrnError) as caught:
        series.read(2)
    message = str(caught.value)
    assert "step 2 (step_032.npy)" in message and "step 0 (step_030.vti)" in message and "\n" not in message

    cth = test_data / "cth_armor_penetration_88x32x32.vtr"
    _copy(cth, tmp_path / "step_032.vtr")
    series = open_series([tmp_path / f"step_{n}.{'vtr' if n == '032' else 'vti'}" for n in STEPS],
                         variable="ImageFile")
    with pytest.raises(ApmgsrnError, match="no array named 'ImageFile'"):
        series.read(2)


def test_a_time_dimension_is_a_series(tmp_path, truth):
    path = tmp_path / "run.nc"
    with VolumeWriter(path, truth.shape[1:], variable="salt", steps=4, time_values=[30, 31, 32, 33]) as writer:
        for t in range(4):
            writer.write(slice(0, 32), truth[t], step=t)
    series = open_series(path, time=parse_time("all"))
    assert len(series) == 4 and series.labels == (0, 1, 2, 3) and series.variable == "salt"
    np.testing.assert_array_equal(series.to_numpy(), truth)
    every_other = open_series(path, time=parse_time("1:4:2"))
    assert [s.time for s in every_other.steps] == [1, 3]
    np.testing.assert_array_equal(every_other.read(1), truth[3])
    with pytest.raises(ApmgsrnError, match="selects no step"):
        open_series(path, time=parse_time("3:3"))
    with pytest.raises(ApmgsrnError, match="reaches past"):
        open_series(path, time=parse_time("0:9"))
    with pytest.raises(ApmgsrnError, match="pass time=all"):
        open_series(path)


def test_parse_time():
    assert parse_time("all") == TimeSelection()
    assert parse_time("7") == 7
    assert parse_time("2:10:3") == TimeSelection(2, 10, 3)
    assert parse_time(":5") == TimeSelection(None, 5, 1)
    assert str(TimeSelection(2, None, 2)) == "2::2"
    for bad in ("x", "1:2:0", "1:2:3:4", "a:b"):
        with pytest.raises(ApmgsrnError, match="time=") as caught:
            parse_time(bad)
        assert caught.value.arguments == ("time",)  # the command line says --time


def test_pvd_collection(tmp_path, step_files, truth):
    for source in step_files:
        _copy(source, tmp_path / source.name)
    entries = "\n".join(
        f'    <DataSet timestep="{0.5 * i}" part="0" file="{f.name}"/>' for i, f in reversed(list(enumerate(step_files)))
    )
    (tmp_path / "run.pvd").write_text(
        f'<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n{entries}\n'
        "  </Collection>\n</VTKFile>\n"
    )
    series = open_series(tmp_path / "run.pvd")
    assert series.labels == (0.0, 0.5, 1.0, 1.5)
    np.testing.assert_array_equal(series.to_numpy(), truth)
    assert is_series_input(str(tmp_path / "run.pvd"))


@pytest.mark.parametrize("text, message", [
    ('<!DOCTYPE x [<!ENTITY a "aaaa">]><VTKFile type="Collection"><Collection/></VTKFile>', "DOCTYPE"),
    ('<VTKFile type="Collection"><Collection></VTKFile>', "not a readable .pvd"),
    ('<VTKFile type="ImageData"></VTKFile>', "not a ParaView collection"),
    ('<VTKFile type="Collection"><Collection/></VTKFile>', "lists no <DataSet>"),
    ('<VTKFile type="Collection"><Collection><DataSet timestep="0" file="missing.vti"/></Collection></VTKFile>',
     "does not exist"),
    ('<VTKFile type="Collection"><Collection><DataSet timestep="0" part="1" file="a.vti"/></Collection></VTKFile>',
     "multi-part"),
])
def test_damaged_pvd_files_are_refused_in_one_line(tmp_path, text, message):
    path = tmp_path / "bad.pvd"
    path.write_text(text)
    with pytest.raises(ApmgsrnError, match=message) as caught:
        open_series(path)
    assert "\n" not in str(caught.value)


def test_what_is_a_series_input(step_files, run_folder):
    assert not is_series_input(str(step_files[0]))
    assert is_series_input([str(f) for f in step_files])
    assert is_series_input(str(run_folder / "*.vti"))
    assert is_series_input(str(step_files[0]), TimeSelection())
    assert not is_series_input(str(step_files[0]), 3)
