"""Hostile and malformed volume files, built on the fly: one line, exit code 2, and nothing allocated
beyond what the file can really hold."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from apmgsrn.cli.main import main
from apmgsrn.data import open_volume
from apmgsrn.errors import ApmgsrnError

pytest.importorskip("vtk")


def vti(path: Path, extent: str, compressor: str = "vtkZLibDataCompressor") -> Path:
    """A tiny ImageData file declaring ``extent`` with three ASCII values in it."""
    attribute = f' compressor="{compressor}"' if compressor else ""
    path.write_text(
        f'<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt64"{attribute}>\n'
        f'  <ImageData WholeExtent="{extent}" Origin="0 0 0" Spacing="1 1 1">\n'
        f'    <Piece Extent="{extent}">\n'
        '      <PointData Scalars="a"><DataArray type="Float32" Name="a" format="ascii">0 1 2</DataArray></PointData>\n'
        "    </Piece>\n  </ImageData>\n</VTKFile>\n"
    )
    return path


@pytest.mark.parametrize("extent,compressor", [("0 2000 0 2000 0 2000", "vtkZLibDataCompressor"),
                                               ("0 99 0 99 0 99", ""),
                                               ("0 2000 0 2000 0 2000", "vtkLZMADataCompressor")])
def test_a_vti_declaring_more_than_it_can_hold_is_refused_before_vtk_allocates(tmp_path, extent, compressor,
                                                                                capsys):
    path = vti(tmp_path / "claims.vti", extent, compressor)
    assert path.stat().st_size < 1000
    with pytest.raises(ApmgsrnError, match="declares"):
        open_volume(path)
    for command in (["train", str(path), "--out", str(tmp_path / "m.apmgsrn")],
                    ["render", str(path), "--out", str(tmp_path / "i.png")]):
        assert main(command) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1
    assert not list(tmp_path.glob("*.apmgsrn")) and not list(tmp_path.glob("*.png"))


@pytest.mark.parametrize("extent", ["0 9 0 x 0 9", "9 0 0 9 0 9"])
def test_a_vti_with_a_malformed_extent_is_refused(tmp_path, extent):
    with pytest.raises(ApmgsrnError, match="extent"):
        open_volume(vti(tmp_path / "bad.vti", extent))


@pytest.mark.parametrize("suffix", [".npy", "_10x9x8_float64.raw"])
def test_float64_values_beyond_float32_are_named_as_such_not_as_nan(tmp_path, suffix, capsys):
    values = np.random.default_rng(0).random((8, 9, 10))
    values[2, 3, 4] = 1e300
    path = tmp_path / f"big{suffix}"
    np.save(path, values) if suffix == ".npy" else values.tofile(path)
    assert main(["train", str(path), "--out", str(tmp_path / "m.apmgsrn"), "--iterations", "2"]) == 2
    err = capsys.readouterr().err
    assert "beyond float32's range" in err and "NaN" not in err and err.count("\n") == 1


@pytest.mark.parametrize("transform", ["none", "log10", "zscore"])
def test_a_constant_volume_decodes_to_exactly_its_value_under_every_transform(tmp_path, transform):
    path = tmp_path / "constant.npy"
    np.save(path, np.full((6, 7, 8), 7.25, dtype=np.float32))
    model = tmp_path / "m.apmgsrn"
    assert main(["train", str(path), "--out", str(model), "--iterations", "3", "--transform", transform]) == 0
    assert main(["decode", str(model), "--out", str(tmp_path / "d.npy")]) == 0
    assert np.unique(np.load(tmp_path / "d.npy")).tolist() == [7.25]
