"""``apmgsrn info``: what a model file holds."""

from __future__ import annotations

import argparse
import json


def register(subparsers) -> None:
    parser = subparsers.add_parser("info", help="describe a model file")
    parser.add_argument("model", help="model file")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(func=run)


def describe_field(field) -> dict:
    """A JSON-able description of a single-field model."""
    import dataclasses

    config = field.config
    info = {
        "model": config.model,
        "encoder": dataclasses.asdict(config.encoder),
        "decoder": dataclasses.asdict(config.decoder),
        "parameters": field.parameter_count(),
        "parameter_bytes": field.parameter_count() * 4,
        "file_bytes": getattr(field, "file_bytes", None),
        "volume_shape_xyz": list(reversed(field.volume_shape)),
        "value_range": [field.value_min, field.value_max],
        "transform": dataclasses.asdict(field.transform),
        "source": getattr(field, "source", {}),
    }
    training = dict(getattr(field, "training_summary", {}) or {})
    history = training.pop("history", None)
    if history and history.get("reconstruction"):
        info["final_reconstruction_loss"] = history["reconstruction"][-1]
    info["training"] = training
    if hasattr(field.encoder, "grid_boxes"):
        boxes = field.encoder.grid_boxes()  # [M, 8, 3]
        info["grids"] = [
            {"center": [round(v, 4) for v in box.mean(0).tolist()],
             "extent": [round(v, 4) for v in (box.max(0).values - box.min(0).values).tolist()]}
            for box in boxes
        ]
    return info


def run(args: argparse.Namespace) -> int:
    import apmgsrn
    from apmgsrn.cli.common import format_bytes

    model = apmgsrn.load(args.model)
    info = describe_field(model)
    if args.json:
        print(json.dumps(info))
        return 0
    enc = info["encoder"]
    t = info["training"]
    print(f"file            {args.model} ({format_bytes(info['file_bytes'])})")
    print(f"model           {info['model']}: " + ", ".join(f"{k}={v}" for k, v in enc.items()))
    print(f"decoder         {info['decoder']['hidden_layers']} x {info['decoder']['width']}, ReLU, no bias")
    print(f"parameters      {info['parameters']:,} ({format_bytes(info['parameter_bytes'])} as float32)")
    x, y, z = info["volume_shape_xyz"]
    print(f"volume          {x}x{y}x{z} (x*y*z) from {info['source'].get('description', '?')}")
    print(f"value range     [{info['value_range'][0]:.6g}, {info['value_range'][1]:.6g}], transform {info['transform']['kind']}")
    if t:
        print(f"training        {t.get('iterations')} iterations x {t.get('batch_size')} points, "
              f"{t.get('seconds')} s on {t.get('device')}, PSNR {t.get('psnr', float('nan')):.2f} dB")
        print(f"final losses    reconstruction {info.get('final_reconstruction_loss', float('nan')):.3e}, "
              f"density {t.get('final_density_loss')}")
        print(f"grids frozen at iteration {t.get('frozen_at')}")
    for i, grid in enumerate(info.get("grids", [])):
        c, e = grid["center"], grid["extent"]
        print(f"  grid {i:2d}  center ({c[0]:+.3f}, {c[1]:+.3f}, {c[2]:+.3f})  extent ({e[0]:.3f}, {e[1]:.3f}, {e[2]:.3f})")
    return 0
