"""ParaView's own colours for every colour-map preset, written to JSON (run with ``pvpython``).

Usage: ``pvpython dump_colors.py REQUEST.json OUT.json``. REQUEST holds ``imports`` (preset files ParaView
imports first: JSON or legacy XML), ``range`` (``[lo, hi]``), ``fractions`` (positions on 0..1) and
``presets_out`` (a path). Every preset ParaView then knows (built-in, then imported) is written to
``presets_out`` as one JSON list, each entry exactly as ParaView prints it. OUT gets, per preset in the
same order, whether applying it made the lookup table categorical and, for presets with ``RGBPoints``,
its colours two ways:

- ``normalized``: applied as ParaView applies a preset (``ApplyPreset(name, rescale=True)``), then
  ``RescaleTransferFunction(lo, hi)``; colours at ``lo + f * (hi - lo)``;
- ``data``: applied keeping the preset's own node positions (``ApplyPreset(name, rescale=False)``);
  colours at ``x0 + f * (x1 - x0)`` over the preset's own span.

Colours come from ``GetTable(v, v, 1)``, the continuous lookup VTK's volume mappers sample (``GetColor``
returns the 256-entry discretised table of surface colouring while ``Discretize`` is on). Presets with
``Points`` also get the opacity of an opacity function given the preset the same two ways. Each preset
goes to a fresh lookup table, so nothing carries over from one to the next; ParaView finds presets by
name and several share one, so a preset whose name came earlier is added again under a unique name.
"""

import json
import sys

import numpy as np
from paraview import servermanager, simple  # noqa: F401  (importing simple connects the session)


def colours(lut, values):
    function = lut.GetClientSideObject()
    table = np.zeros(3)
    out = []
    for v in values:
        function.GetTable(float(v), float(v), 1, table)
        out.append(table.tolist())
    return out


def opacities(pwf, values):
    function = pwf.GetClientSideObject()
    return [function.GetValue(float(v)) for v in values]


def main(request_path, out_path):
    with open(request_path) as handle:
        request = json.load(handle)
    lo, hi = request["range"]
    fractions = np.asarray(request["fractions"], dtype=np.float64)
    presets = servermanager.vtkSMTransferFunctionPresets.GetInstance()
    builtin_count = presets.GetNumberOfPresets()
    imported = {}
    for path in request.get("imports", []):
        before = presets.GetNumberOfPresets()
        presets.ImportPresets(path)
        imported[path] = presets.GetNumberOfPresets() - before
    texts = [presets.GetPresetAsString(index) for index in range(presets.GetNumberOfPresets())]
    with open(request["presets_out"], "w") as handle:
        handle.write("[\n" + ",\n".join(texts) + "\n]\n")
    out = {"builtin_count": builtin_count, "imported": imported, "presets": []}
    seen = set()
    for index, text in enumerate(texts):
        preset = json.loads(text)
        name = presets.GetPresetName(index)
        unique = name
        if name in seen:
            unique = f"apmgsrn check {index}"
            presets.AddPreset(unique, text)
        seen.add(name)
        lut = servermanager.rendering.PVLookupTable()
        entry = {"name": name, "applied": bool(lut.ApplyPreset(unique, True))}
        entry["categorical"] = bool(lut.InterpretValuesAsCategories)
        if "RGBPoints" in preset:
            lut.RescaleTransferFunction(lo, hi)
            values = lo + fractions * (hi - lo)
            entry["normalized"] = {"values": values.tolist(), "rgb": colours(lut, values),
                                   "rgb_points": list(lut.RGBPoints)}
            kept = servermanager.rendering.PVLookupTable()
            kept.ApplyPreset(unique, False)
            xs = preset["RGBPoints"][0::4]
            values = min(xs) + fractions * (max(xs) - min(xs))
            entry["data"] = {"values": values.tolist(), "rgb": colours(kept, values),
                             "log_scale": bool(kept.UseLogScale)}
            if "Points" in preset:
                pwf = servermanager.piecewise_functions.PiecewiseFunction()
                pwf.ApplyPreset(unique, True)
                pwf.RescaleTransferFunction(lo, hi)
                entry["normalized"]["opacity"] = opacities(pwf, entry["normalized"]["values"])
                pwf = servermanager.piecewise_functions.PiecewiseFunction()
                pwf.ApplyPreset(unique, False)
                entry["data"]["opacity"] = opacities(pwf, entry["data"]["values"])
        out["presets"].append(entry)
    with open(out_path, "w") as handle:
        handle.write(json.dumps(out))  # dumps: json.dump streams through the slow pure-Python encoder


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
