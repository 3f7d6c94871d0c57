"""``apmgsrn grids``: pictures of where an APMGSRN model placed its grids."""

from __future__ import annotations

import argparse
from pathlib import Path

import apmgsrn
from apmgsrn.cli.common import add_data_arguments, add_device_argument, open_data
from apmgsrn.cli.paths import CommandPaths, Output
from apmgsrn.errors import ApmgsrnError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "grids",
        help="draw the learned grid boxes over the volume; VTK boxes for ParaView; optional animation",
        description="Write PREFIX.png (grid boxes over maximum-intensity projections along z, y and x) and "
        "PREFIX.vtk (the boxes as hexahedra, in voxel-index coordinates, for ParaView). With --animate, "
        "train the model again with its recorded settings and seed, record the grids every K iterations "
        "and write PREFIX.gif. Files of those names are replaced, unless one is an input or an apmgsrn model.",
    )
    parser.add_argument("model", help="an apmgsrn model file")
    parser.add_argument("data", help="the volume the model was trained on")
    add_data_arguments(parser)
    parser.add_argument("--out", required=True, metavar="PREFIX", help="output path prefix (PREFIX.png, ...)")
    parser.add_argument("--vtk-coordinates", choices=["index", "normalized"], default="index",
                        help="VTK box coordinates: voxel index (default, lines up in ParaView) or [-1, 1]")
    parser.add_argument("--animate", action="store_true", help="also write PREFIX.gif of the grids in training")
    parser.add_argument("--every", type=int, default=50, metavar="K", help="animation: a frame every K iterations")
    parser.add_argument("--iterations", type=int, help="animation: train this many iterations instead")
    add_device_argument(parser)
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    suffixes = (".png", ".vtk", ".gif") if args.animate else (".png", ".vtk")
    writes = [Output(f"{args.out}{suffix}", "--out", f"{suffix[1:]} file") for suffix in suffixes]
    return CommandPaths(reads=[args.model, args.data], writes=writes)


def run(args: argparse.Namespace) -> int:
    from apmgsrn.bench.grid_pictures import (
        grid_picture,
        projections,
        record_grid_history,
        require_grids,
        write_grid_animation,
        write_grid_vtk,
    )
    from apmgsrn.device import resolve_device
    from apmgsrn.inference.evaluate import check_volume_shape

    prefix = Path(args.out)
    if not prefix.absolute().parent.is_dir():
        raise ApmgsrnError(f"{prefix}: output folder {prefix.parent} does not exist; create it or choose another --out")
    model = apmgsrn.load(args.model)
    boxes = require_grids(model.field, args.model)
    volume = open_data(args, args.data)
    check_volume_shape(volume.shape, model.description.volume_shape, args.data)
    # The replay first: it refuses its settings before anything is written.
    history = None
    if args.animate:
        history = record_grid_history(
            model, volume, args.every, resolve_device(args.device), args.iterations,
            log=lambda line: print(line, flush=True),
        )
    mips = projections(volume, model.field.transform)
    title = f"{Path(args.model).name}: {boxes.shape[0]} grids over {volume.describe()}"
    png, vtk = Path(f"{prefix}.png"), Path(f"{prefix}.vtk")
    grid_picture(boxes, mips, png, title)
    write_grid_vtk(boxes, vtk, volume.shape if args.vtk_coordinates == "index" else None)
    print(f"wrote {png} and {vtk}")
    if history is not None:
        gif = Path(f"{prefix}.gif")
        frames = write_grid_animation(history, mips, gif, Path(args.model).name)
        print(f"wrote {gif} ({frames} frames)")
    return 0
