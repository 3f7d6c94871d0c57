"""ParaView reader plugin for apmgsrn models: open a ``.apmgsrn`` file, or a brick model's ``manifest.json``, as
image data at a chosen resolution, region and time step, named, placed and spaced as the training volume was.

Load it with Tools > Manage Plugins > Load New (this file), or put its folder on ``PV_PLUGIN_PATH``. It works
with ParaView 5.11 (Debian's ``paraview``) and later releases.

ParaView runs its own Python, whose numpy and version need not match the environment apmgsrn and PyTorch are
installed in (mixing compiled packages across the two fails, or crashes). So this file imports nothing of
apmgsrn: it runs apmgsrn's own command line in that environment (``apmgsrn decode ... --out FILE.vti``, which
writes the volume with origin, spacing and the variable's name) and reads the result with VTK's reader. It
finds the environment through, in this order:

- ``APMGSRN_PYTHON``: the Python interpreter that has apmgsrn installed (``/path/to/.venv/bin/python``);
- ``APMGSRN_VENV``: the virtual environment's folder (its ``bin/python``, ``Scripts\\python.exe`` on Windows);
- the ``apmgsrn`` command on ``PATH``.

ParaView's own ``PYTHONPATH`` and ``PYTHONHOME`` are not passed on (they would make the environment's Python
import ParaView's packages); ``APMGSRN_PYTHONPATH``, if set, becomes the command's ``PYTHONPATH``.
"""

import atexit
import json
import os
import shutil
import subprocess
import tempfile

from paraview.util.vtkAlgorithm import VTKPythonAlgorithmBase, smdomain, smhint, smproperty, smproxy
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline
from vtkmodules.vtkIOXML import vtkXMLImageDataReader

PYTHON_VARIABLE = "APMGSRN_PYTHON"
VENV_VARIABLE = "APMGSRN_VENV"
PYTHONPATH_VARIABLE = "APMGSRN_PYTHONPATH"
MANIFEST_NAME = "manifest.json"


def apmgsrn_command():
    """The command line that runs apmgsrn in its own environment, as a list."""
    python = os.environ.get(PYTHON_VARIABLE)
    if python:
        return [python, "-m", "apmgsrn"]
    venv = os.environ.get(VENV_VARIABLE)
    if venv:
        python = os.path.join(venv, "Scripts", "python.exe") if os.name == "nt" else os.path.join(venv, "bin", "python")
        return [python, "-m", "apmgsrn"]
    found = shutil.which("apmgsrn")
    if found:
        return [found]
    raise RuntimeError(
        "apmgsrn reader: cannot find apmgsrn; set APMGSRN_VENV to the virtual environment where it is installed "
        "(or APMGSRN_PYTHON to its python), then restart ParaView"
    )


def run_apmgsrn(arguments):
    """Run ``apmgsrn ARGUMENTS`` and return its standard output.

    Raises:
        RuntimeError: it failed; the message is apmgsrn's own (``error: ...``).
    """
    environment = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    if os.environ.get(PYTHONPATH_VARIABLE):
        environment["PYTHONPATH"] = os.environ[PYTHONPATH_VARIABLE]
    done = subprocess.run(apmgsrn_command() + list(arguments), capture_output=True, text=True, env=environment)
    if done.returncode != 0:
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        raise RuntimeError("apmgsrn reader: " + (lines[-1] if lines else f"apmgsrn exited with {done.returncode}"))
    return done.stdout


def model_path(file_name):
    """The model a chosen file stands for (a brick model is opened through its folder's manifest), as an
    absolute path: it starts with ``/``, so the command line never reads a file named ``-h`` as an option."""
    path = os.path.abspath(file_name)
    return os.path.dirname(path) if os.path.basename(path) == MANIFEST_NAME else path


#: Folders of decoded volumes not yet removed. A reader removes its folder when it decodes again or is
#: collected, but ParaView does not always collect its readers before it exits: what is left goes at exit.
_FOLDERS = set()


def _remove(folder):
    shutil.rmtree(folder, ignore_errors=True)
    _FOLDERS.discard(folder)


@atexit.register
def _remove_all():
    for folder in list(_FOLDERS):
        _remove(folder)


@smproxy.reader(name="ApmgsrnReader", label="apmgsrn model", extensions="apmgsrn",
                filename_patterns=MANIFEST_NAME, file_description="apmgsrn model")
class ApmgsrnReader(VTKPythonAlgorithmBase):
    """An apmgsrn model sampled on a lattice, as image data (one point array, the source's variable)."""

    def __init__(self):
        VTKPythonAlgorithmBase.__init__(self, nInputPorts=0, nOutputPorts=1, outputType="vtkImageData")
        self._file_name = None
        self._resolution = (0, 0, 0)
        self._region = (0, -1, 0, -1, 0, -1)
        self._time = None  # the time step decoded (None: the model's first)
        self._decoded = None  # (settings, apmgsrn's report, the .vti it wrote)

    # ---------------------------------------------------------------------------------------- properties
    @smproperty.stringvector(name="FileName")
    @smdomain.filelist()
    @smhint.filechooser(extensions="apmgsrn", file_description="apmgsrn model")
    def SetFileName(self, name):
        if name != self._file_name:
            self._file_name = name
            self.Modified()

    @smproperty.intvector(name="Resolution", default_values=[0, 0, 0])
    @smdomain.xml('<Documentation>Samples along x, y and z; 0 0 0: the training volume\'s spacing over the '
                  'region.</Documentation>')
    def SetResolution(self, x, y, z):
        if (x, y, z) != self._resolution:
            self._resolution = (x, y, z)
            self.Modified()

    @smproperty.intvector(name="Region", default_values=[0, -1, 0, -1, 0, -1])
    @smdomain.xml('<Documentation>Voxels of the training volume to decode, as an extent: x0 x1 y0 y1 z0 z1, '
                  'both ends included; -1 as an end: the last voxel.</Documentation>')
    def SetRegion(self, x0, x1, y0, y1, z0, z1):
        if (x0, x1, y0, y1, z0, z1) != self._region:
            self._region = (x0, x1, y0, y1, z0, z1)
            self.Modified()

    @smproperty.doublevector(name="TimestepValues", information_only="1", si_class="vtkSITimeStepsProperty")
    def GetTimestepValues(self):
        decoded = self._decode(self._time)
        steps = decoded[0]["time_steps"] if decoded else 1
        return list(range(steps)) if steps > 1 else None

    # ------------------------------------------------------------------------------------------ decoding
    def _arguments(self):
        """apmgsrn decode's arguments for the chosen resolution and region (output path excluded)."""
        arguments = [model_path(self._file_name)]
        if all(n > 0 for n in self._resolution):
            arguments += ["--shape", ",".join(str(n) for n in self._resolution)]
        if self._region != (0, -1, 0, -1, 0, -1):
            parts = []
            for axis in range(3):
                start, end = self._region[2 * axis], self._region[2 * axis + 1]
                parts.append(f"{start}:" + ("" if end < 0 else str(end + 1)))  # inclusive end -> slicing's stop
            arguments.append("--region=" + ",".join(parts))
        return arguments

    def _decode(self, time=None):
        """The decoded volume for the current settings and time step: apmgsrn's report (lattice, origin, spacing,
        time steps) and the ``.vti`` it wrote. One decode per setting: the pipeline asks for information before
        data, and both come from the same run; only the latest decode is kept on disk."""
        if not self._file_name:
            return None
        key = (self._file_name, os.path.getmtime(self._file_name), tuple(self._arguments()), time)
        if self._decoded is None or self._decoded[0] != key:
            self._forget()
            folder = tempfile.mkdtemp(prefix="apmgsrn-paraview-")
            _FOLDERS.add(folder)
            out = os.path.join(folder, "decoded.vti")
            arguments = ["decode", *self._arguments(), "--out", out, "--json"]
            try:
                report = json.loads(run_apmgsrn(arguments + ([] if time is None else ["--time", str(time)])))
            except BaseException:
                _remove(folder)
                raise
            self._decoded = (key, report, out)
        return self._decoded[1], self._decoded[2]

    def _forget(self):
        if self._decoded is not None:
            _remove(os.path.dirname(self._decoded[2]))
            self._decoded = None

    def __del__(self):
        try:
            self._forget()
        except Exception:  # noqa: BLE001 - at interpreter exit the modules may already be gone
            pass

    def RequestInformation(self, request, inInfo, outInfo):
        decoded = self._decode(self._time)
        if decoded is None:
            return 0
        report = decoded[0]
        x, y, z = report["shape_xyz"]
        info = outInfo.GetInformationObject(0)
        info.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), 0, x - 1, 0, y - 1, 0, z - 1)
        steps = report["time_steps"]
        if steps > 1:
            info.Set(vtkStreamingDemandDrivenPipeline.TIME_STEPS(), list(range(steps)), steps)
            info.Set(vtkStreamingDemandDrivenPipeline.TIME_RANGE(), [0, steps - 1], 2)
        return 1

    def RequestData(self, request, inInfo, outInfo):
        info = outInfo.GetInformationObject(0)
        report, _ = self._decode(self._time)
        if report["time_steps"] > 1 and info.Has(vtkStreamingDemandDrivenPipeline.UPDATE_TIME_STEP()):
            wanted = info.Get(vtkStreamingDemandDrivenPipeline.UPDATE_TIME_STEP())
            self._time = min(max(int(round(wanted)), 0), report["time_steps"] - 1)  # the nearest step
        _, out = self._decode(self._time)
        reader = vtkXMLImageDataReader()
        reader.SetFileName(out)
        reader.Update()
        vtkImageData.GetData(outInfo, 0).ShallowCopy(reader.GetOutput())
        return 1
