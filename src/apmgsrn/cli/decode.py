"""``apmgsrn decode``: reconstruct the volume from a model to NetCDF, VTK ImageData, raw or .npy, chunk by chunk,
with the variable name, attributes, dimension names, coordinates and compression its source had."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import apmgsrn
from apmgsrn.choices import REGION_UNITS
from apmgsrn.arguments import parse_triple
from apmgsrn.cli.common import add_device_argument, add_precision_argument
from apmgsrn.options import time_value
from apmgsrn.cli.paths import CommandPaths, Output
from apmgsrn.errors import ApmgsrnError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "decode", help="reconstruct a volume file from a model",
        description="Sample a model on a lattice (the training volume's, another resolution, a region) and write "
                    "it with the source's variable name, units and attributes, dimension names and coordinates "
                    "(rescaled to the lattice) and compression.",
    )
    parser.add_argument("model", help="model file or brick-model folder")
    parser.add_argument("--out", required=True,
                        help="output volume (.nc, .vti, .raw or .npy); a file of that name is replaced once the "
                             "volume is complete, unless it is the model or another apmgsrn model")
    parser.add_argument("--shape", help="X,Y,Z output resolution (default: the training volume's spacing over the "
                                        "region)")
    parser.add_argument("--region", metavar="X0:X1,Y0:Y1,Z0:Z1",
                        help="decode only this box: voxel indices of the training volume, half-open as in slicing "
                             "(e.g. 10:40,:,0:16), or coordinates with --region-units coordinates")
    parser.add_argument("--region-units", choices=REGION_UNITS, default="index",
                        help="index (default): --region in voxel indices; coordinates: a closed box in the "
                             "source's coordinates")
    parser.add_argument("--time", type=time_value, metavar="K|all|A:B[:S]",
                        help="time step to decode (default: the first; required for a time-series model); "
                             "several steps of a time-series model go to one file with a time axis (.nc, .raw, "
                             ".npy), or one file per step when --out holds {step}")
    parser.add_argument("--batch-size", type=int, default=2**18, help="points per forward pass")
    parser.add_argument("--dry-run", action="store_true",
                        help="write nothing: say what would be written (lattice, origin, spacing, variable)")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_device_argument(parser)
    add_precision_argument(parser, "float32", "")
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    return CommandPaths(reads=[args.model], writes=[Output(args.out, "--out", "decoded volume")])


def run(args: argparse.Namespace) -> int:
    from apmgsrn.data.grid import Region
    from apmgsrn.series.data import TimeSelection
    from apmgsrn.data.writers import check_axes_writable
    from apmgsrn.io.description import time_steps

    model = apmgsrn.load(args.model, device=args.device, precision=args.precision)
    shape = None
    if args.shape:
        x, y, z = parse_triple(args.shape, "shape")
        shape = (z, y, x)
    region = Region.parse(args.region, args.region_units) if args.region else None
    time = args.time
    if model.description.series is not None:
        from apmgsrn.cli.series import STEP_FIELD, model_step, run_series_decode

        if isinstance(time, TimeSelection) or STEP_FIELD in str(args.out):
            return run_series_decode(args, model, shape, region)
        time = model_step(model, time)  # a series has no default step
    elif isinstance(time, TimeSelection):
        raise ApmgsrnError(f"--time {time} selects several steps, but {args.model} holds one volume; drop --time")
    out = Path(args.out)
    if args.dry_run:
        plan = model.plan_decode(shape=shape, region=region, time=time)
        check_axes_writable(out, plan.axes)
    else:
        plan = model.save_decoded(out, shape=shape, region=region, time=time, batch_size=args.batch_size,
                                  progress=not args.json)
    d, h, w = plan.shape
    report = {"out": str(out), "written": not args.dry_run, "shape_xyz": [w, h, d], "variable": plan.variable,
              "origin": list(plan.origin), "spacing": list(plan.spacing), "time": plan.time,
              "time_steps": time_steps(model.description), "value_range": list(model.description.value_range),
              "units": model.description.source.metadata.units}
    if args.json:
        print(json.dumps(report))
    elif args.dry_run:
        print(f"would write {out} ({w}x{h}x{d} x*y*z, float32, variable {plan.variable}), origin "
              f"{', '.join(f'{v:g}' for v in plan.origin)}, spacing {', '.join(f'{v:g}' for v in plan.spacing)}")
    else:
        print(f"wrote {out} ({w}x{h}x{d} x*y*z, float32, variable {plan.variable})")
    return 0
