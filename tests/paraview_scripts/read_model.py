"""Open a model through the apmgsrn reader plugin in ParaView and write what ParaView got (run with pvpython).

Usage: ``pvpython read_model.py PLUGIN.py REQUESTS.json``. REQUESTS is a list; each request holds ``file`` (a
model file or a brick model's manifest.json), ``out`` (a folder) and optionally ``resolution`` (``[x, y, z]``)
and ``region`` (an inclusive voxel extent ``[x0, x1, y0, y1, z0, z1]``). Each ``out`` gets ``values.npy`` (the
point array, [z, y, x]) and ``grid.json`` (reader, array name, dimensions, origin, spacing, extent, arrays).
"""

import inspect
import json
import os
import sys

# Debian's ParaView 5.11 runs Python 3.11, whose inspect has no getargspec, which ParaView's Python-plugin
# loader imports: no Python plugin loads until it is put back (docs/paraview.md gives users the same line).
if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec

import numpy as np
from paraview import servermanager, simple
from vtkmodules.util.numpy_support import vtk_to_numpy


def main(plugin, requests_path):
    with open(requests_path) as handle:
        requests = json.load(handle)
    simple.LoadPlugin(plugin, remote=False, ns=globals())
    for request in requests:
        read(request, request["out"])


def read(request, out):
    reader = simple.OpenDataFile(request["file"])  # ParaView picks the reader by the file name, as the GUI does
    if "resolution" in request:
        reader.Resolution = request["resolution"]
    if "region" in request:
        reader.Region = request["region"]
    reader.UpdatePipeline()
    data = servermanager.Fetch(reader)
    points = data.GetPointData()
    array = points.GetArray(0)
    nx, ny, nz = data.GetDimensions()
    np.save(os.path.join(out, "values.npy"), vtk_to_numpy(array).reshape(nz, ny, nx))
    grid = {
        "reader": reader.GetXMLName(),
        "name": array.GetName(),
        "arrays": points.GetNumberOfArrays(),
        "dimensions": [nx, ny, nz],
        "origin": list(data.GetOrigin()),
        "spacing": list(data.GetSpacing()),
        "extent": list(data.GetExtent()),
    }
    with open(os.path.join(out, "grid.json"), "w") as handle:
        json.dump(grid, handle)


if __name__ == "__main__":
    main(*sys.argv[1:3])
