"""``apmgsrn render``: volume-render a model or a volume to an image, a comparison or a turntable."""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from apmgsrn.limits import LIMITS
from apmgsrn.arguments import int_type
from apmgsrn.choices import PRESET_UNITS
from apmgsrn.cli.common import add_data_arguments, add_device_argument
from apmgsrn.cli.paths import CommandPaths, Output
from apmgsrn.errors import ApmgsrnError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "render",
        help="volume-render a model or a volume (image, comparison, turntable)",
        description=(
            "Ray-march a model file (single or brick model) or any volume the reader supports (rendered from "
            "its voxels: the reference image) with a colour map and an opacity map. Opacity is corrected for "
            "the step length, empty space is skipped and rays stop once opaque."
        ),
    )
    parser.add_argument("input", metavar="MODEL_OR_DATA", help="model file or volume file")
    parser.add_argument("--out", required=True,
                        help="image (.png) or, with --frames, animation (.gif, .mp4); a file of that name is "
                             "replaced once the image is complete, unless it is an input or an apmgsrn model")
    view = parser.add_argument_group("camera")
    view.add_argument("--width", type=int, default=512, help="image width in pixels (default 512)")
    view.add_argument("--height", type=int, default=512, help="image height in pixels (default 512)")
    view.add_argument("--azimuth", type=float, default=30.0, help="degrees around +z; 0 looks from -y (default 30)")
    view.add_argument("--elevation", type=float, default=20.0, help="degrees above the xy plane (default 20)")
    view.add_argument("--distance", type=float, help="camera distance from the centre (default: fit the box)")
    view.add_argument("--fov", type=float, default=30.0, help="vertical field of view, degrees (default 30)")
    view.add_argument("--no-aspect", action="store_true",
                      help="draw the box as a cube instead of with the volume's proportions")
    tf = parser.add_argument_group("transfer function")
    tf.add_argument("--colormap", default="Cool to Warm",
                    help="built-in name (Cool to Warm, viridis, plasma, coolwarm, grayscale, jet, ... any "
                         "matplotlib name) or a ParaView preset .json/.xml file (default: Cool to Warm)")
    tf.add_argument("--preset-name", help="which preset of a file holding several (default: the first)")
    tf.add_argument("--preset-units", choices=PRESET_UNITS, default="normalized",
                    help="normalized: stretch the preset over the range, as ParaView applies presets "
                         "(default); data: keep its node positions, e.g. a transfer function saved from a session")
    tf.add_argument("--opacity", metavar="X0,A0,X1,A1,...",
                    help="opacity nodes: positions on 0..1 of the range and their opacity per reference step "
                         "(default: a preset's own, else 0,0,1,1)")
    tf.add_argument("--range", metavar="MIN,MAX", help="value range of the transfer function, data units "
                    "(default: the model's or volume's min and max)")
    tf.add_argument("--background", default="white", help="white (default), black, or R,G,B in 0..1")
    tf.add_argument("--save-tf", metavar="FILE.json", help="also write the transfer function as a ParaView preset")
    march = parser.add_argument_group("ray marching")
    march.add_argument("--spp", type=int, default=256,
                       help="samples per ray across the box's longest side (default 256)")
    march.add_argument("--reference-samples", type=int, default=256,
                       help="opacities are per step of (longest side / this) (default 256)")
    march.add_argument("--batch-size", type=int,
                       help="most points per forward pass; bounds memory (default 262144 on CPU, 1048576 on GPU)")
    march.add_argument("--early-termination", type=float, default=1e-3,
                       help="stop a ray once its transmittance falls below this; 0 never (default 1e-3)")
    march.add_argument("--no-skipping", action="store_true", help="turn empty-space skipping off")
    march.add_argument("--macro-cells", type=int, default=32, help="macro cells per axis for skipping (default 32)")
    march.add_argument("--jitter", action="store_true", help="seeded per-pixel random ray offsets (less banding)")
    march.add_argument("--seed", type=int, default=0, help="seed of --jitter")
    extra = parser.add_argument_group("comparison and animation")
    extra.add_argument("--compare", metavar="DATA",
                       help="also render this volume with the same camera and transfer function; print PSNR "
                            "and SSIM, write the pair side by side to --out and the error to --error-out")
    extra.add_argument("--error-out", help="error image of --compare (default: OUT_error.png)")
    extra.add_argument("--frames", type=int_type(1, LIMITS.frames),
                       help=f"write a turntable animation of N frames to --out (.gif/.mp4; at most {LIMITS.frames})")
    extra.add_argument("--fps", type=float, default=15.0, help="frames per second of --frames (default 15)")
    add_data_arguments(parser)
    add_device_argument(parser)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    """Reads the model or volume, the --compare volume and a preset file; writes the image (and error
    image), animation and --save-tf preset."""
    reads = [args.input, args.compare]
    if Path(args.colormap).suffix.lower() in (".json", ".xml"):
        reads.append(args.colormap)
    writes = [Output(args.out, "--out", "image")]
    if args.compare:
        writes.append(Output(error_image_path(args), "--error-out", "error image", suffixes=(".png",)))
    if args.save_tf:
        writes.append(Output(args.save_tf, "--save-tf", "transfer function", suffixes=(".json",)))
    return CommandPaths(reads=reads, writes=writes)


def error_image_path(args: argparse.Namespace) -> Path:
    """``--error-out``, else ``OUT_error.png`` beside ``--out``."""
    out = Path(args.out)
    return Path(args.error_out) if args.error_out else out.with_name(out.stem + "_error.png")


def run(args: argparse.Namespace) -> int:
    # torch and the renderer load here, not when the CLI starts.
    from apmgsrn.device import resolve_device
    from apmgsrn.rendering import Camera, RendererConfig, image_psnr, image_ssim, make_transfer_function
    from apmgsrn.rendering.animation import render_frames, turntable_cameras, write_animation
    from apmgsrn.rendering.images import as_uint8, error_image, save_image, side_by_side
    from apmgsrn.rendering.paraview import save_transfer_function
    from apmgsrn.rendering.raymarch import default_batch_size
    from apmgsrn.sources import SourceOptions, open_source

    from apmgsrn.cli.series import render_steps

    out = Path(args.out)
    volume, first_step, time_steps = render_steps(args)
    if time_steps and args.frames is not None:
        raise ApmgsrnError("--time with several steps animates over time (one frame per step); drop --frames")
    animate = args.frames is not None or bool(time_steps)
    if animate and args.compare:
        raise ApmgsrnError("--frames and --compare cannot be combined; run them separately")
    if animate and out.suffix.lower() not in (".gif", ".mp4"):
        raise ApmgsrnError(f"{out}: an animation (--frames, or --time over several steps) must be a .gif or .mp4 file")
    if not animate and out.suffix.lower() != ".png":
        raise ApmgsrnError(f"{out}: the output image must be a .png file (or use --frames with .gif/.mp4)")
    if not (out.parent if str(out.parent) else Path(".")).is_dir():
        raise ApmgsrnError(f"{out}: folder {out.parent} does not exist; create it first")

    device = resolve_device(args.device)
    if args.batch_size is None:
        args.batch_size = default_batch_size(device)
    config = RendererConfig(
        samples_per_ray=args.spp,
        reference_samples=args.reference_samples,
        batch_size=args.batch_size,
        early_termination=args.early_termination,
        empty_space_skipping=not args.no_skipping,
        macro_cells=args.macro_cells,
        jitter=args.jitter,
        seed=args.seed,
        background=parse_background(args.background),
    )
    options = SourceOptions(volume=volume, step=first_step)
    source = open_source(args.input, device, options)
    value_range = parse_range(args.range) if args.range else source.value_range
    opacity = parse_opacity(args.opacity) if args.opacity else None
    transfer_function = make_transfer_function(
        args.colormap, value_range, opacity=opacity, preset_name=args.preset_name, preset_units=args.preset_units
    )
    if args.range and args.preset_units == "data":
        transfer_function = transfer_function.rescaled(*value_range)  # an explicit range always wins
    extent = (1.0, 1.0, 1.0) if args.no_aspect else source.extent
    renderer = source.renderer(transfer_function, config, extent)
    report: dict = {"input": args.input, "out": str(out), "device": str(device)}
    if source.series is not None:
        report["step"] = source.step
    if args.save_tf:
        save_transfer_function(transfer_function, args.save_tf)
        report["transfer_function"] = args.save_tf

    if time_steps:
        camera = Camera.orbit(args.azimuth, args.elevation, args.distance, args.fov, args.width, args.height, extent)
        start = time.perf_counter()
        frames = (as_uint8(source.at_step(k).renderer(transfer_function, config, extent).render(camera).image)
                  for k in time_steps)
        write_animation(frames, out, fps=args.fps)
        report.update(frames=len(time_steps), steps=time_steps, seconds=round(time.perf_counter() - start, 3))
        return _finish(args, report, f"wrote {out} ({len(time_steps)} time steps, {args.width}x{args.height}) "
                                     f"in {report['seconds']:.1f} s")

    if animate:
        cameras = turntable_cameras(
            args.frames, args.azimuth, args.elevation, args.distance, args.fov, args.width, args.height, extent
        )
        start = time.perf_counter()
        write_animation(render_frames(renderer, cameras), out, fps=args.fps)
        report.update(frames=args.frames, seconds=round(time.perf_counter() - start, 3))
        return _finish(args, report, f"wrote {out} ({args.frames} frames, {args.width}x{args.height}) "
                                     f"in {report['seconds']:.1f} s")

    camera = Camera.orbit(args.azimuth, args.elevation, args.distance, args.fov, args.width, args.height, extent)
    start = time.perf_counter()
    result = renderer.render(camera)
    seconds = time.perf_counter() - start
    stats = result.statistics
    skipped = 1.0 - stats.field_evaluations / stats.samples_in_box if stats.samples_in_box else 0.0
    report.update(
        width=args.width,
        height=args.height,
        spp=args.spp,
        seconds=round(seconds, 3),
        field_evaluations=stats.field_evaluations,
        samples_in_box=stats.samples_in_box,
        visible_cells=renderer.visible_fraction,
    )
    if not args.compare:
        save_image(result.image, out)
        return _finish(args, report, f"wrote {out} ({args.width}x{args.height}, {args.spp} spp) in {seconds:.2f} s; "
                                     f"field evaluated at {stats.field_evaluations:,} of {stats.samples_in_box:,} "
                                     f"samples in the box ({100 * skipped:.0f}% skipped or past opacity)")

    reference_source = open_source(args.compare, device, options)
    reference = reference_source.renderer(transfer_function, config, extent).render(camera).image
    psnr = image_psnr(result.image, reference)
    ssim = image_ssim(result.image, reference) if min(args.width, args.height) >= 11 else float("nan")
    save_image(side_by_side(result.image, reference), out)
    error_path = error_image_path(args)
    error, scale = error_image(result.image, reference)
    save_image(error, error_path)
    report.update(compare=args.compare, psnr=psnr, ssim=ssim, error_image=str(error_path), error_scale=scale)
    return _finish(
        args,
        report,
        f"PSNR {psnr:.2f} dB\nSSIM {ssim:.4f}\nwrote {out} (left: {args.input}, right: {args.compare}) and "
        f"{error_path} (mean |error| over RGB, full colour scale = {scale:.3g})",
    )


def _finish(args: argparse.Namespace, report: dict, text: str) -> int:
    if args.json:
        clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in report.items()}
        print(json.dumps(clean))
    else:
        print(text)
    return 0


def _floats(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ApmgsrnError(f"{option} {text!r}: expected comma-separated numbers") from None
    if not all(math.isfinite(v) for v in values):
        raise ApmgsrnError(f"{option} {text!r}: numbers must be finite")
    return values


def parse_range(text: str) -> tuple[float, float]:
    """``"MIN,MAX"`` -> (MIN, MAX), MIN < MAX."""
    values = _floats(text, "--range")
    if len(values) != 2 or not values[0] < values[1]:
        raise ApmgsrnError(f"--range {text!r}: expected MIN,MAX with MIN < MAX")
    return values[0], values[1]


def parse_opacity(text: str) -> tuple[tuple[float, float], ...]:
    """``"x0,a0,x1,a1,..."`` -> pairs; positions ascending in [0, 1], opacities in [0, 1]."""
    values = _floats(text, "--opacity")
    if len(values) < 2 or len(values) % 2:
        raise ApmgsrnError(f"--opacity {text!r}: expected pairs X,ALPHA like 0,0,1,0.5")
    pairs = tuple((values[i], values[i + 1]) for i in range(0, len(values), 2))
    xs = [x for x, _ in pairs]
    if any(b < a for a, b in zip(xs, xs[1:])):
        raise ApmgsrnError(f"--opacity {text!r}: positions must be in increasing order")
    if not all(0.0 <= x <= 1.0 and 0.0 <= a <= 1.0 for x, a in pairs):
        raise ApmgsrnError(f"--opacity {text!r}: positions (0..1 of the range) and opacities must lie in [0, 1]")
    return pairs


def parse_background(text: str) -> tuple[float, float, float]:
    """``white``, ``black`` or ``R,G,B`` (0..1) -> an RGB triple."""
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
    if text.strip().lower() in named:
        return named[text.strip().lower()]
    values = _floats(text, "--background")
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise ApmgsrnError(f"--background {text!r}: use white, black or R,G,B with each in 0..1")
    return values[0], values[1], values[2]
