"""Hostile and malformed volume files, built on the fly: one line, exit code 2, and nothing allocated
beyond what the file can really hold."""

from __future__ import annotations

from pathlib import Path

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
