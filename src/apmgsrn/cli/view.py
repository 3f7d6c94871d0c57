"""``apmgsrn view``: serve the interactive viewer (a web page) for a model, a volume or a folder of them."""

from __future__ import annotations

import argparse
import importlib.util
import socket
import sys
from pathlib import Path

from apmgsrn.cli.common import add_device_argument
from apmgsrn.errors import ApmgsrnError

LOOPBACK = "127.0.0.1"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "view",
        help="serve the interactive viewer (web page) for models and volumes",
        description=(
            "Serve a web page that volume-renders a model, a volume, or any model and volume in a folder, "
            "with orbit/pan/zoom, progressive refinement, colour maps (built-in, ParaView presets in the "
            "folder, uploads), an opacity editor, statistics, frame and transfer-function saving, and an "
            "overlay of the learned feature grids. Binds to 127.0.0.1: from a laptop, reach a cluster node "
            "with 'ssh -L PORT:127.0.0.1:PORT node' and open the printed URL."
        ),
    )
    parser.add_argument("path", nargs="?", default=".", metavar="PATH",
                        help="model file, volume file, or folder to list (default: the current folder)")
    parser.add_argument("--port", type=int, default=8080, help="port to listen on (default 8080; 0 picks a free one)")
    parser.add_argument("--host", default=LOOPBACK,
                        help="interface to bind (default 127.0.0.1; anything else exposes the page to the network)")
    parser.add_argument("--save-dir", default="apmgsrn-view",
                        help="folder for server-side copies of saved frames and transfer functions "
                             "(default: ./apmgsrn-view, created on first save)")
    parser.add_argument("--image-size", type=int, default=None,
                        help="starting image size in pixels (default 256 on CPU, 512 on GPU)")
    parser.add_argument("--spp", type=int, default=128, help="starting samples per ray (default 128)")
    add_device_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 0 <= args.port <= 65535:
        raise ApmgsrnError(f"--port {args.port} is not a port number (0..65535)")
    if args.image_size is not None and not 16 <= args.image_size <= 2048:
        raise ApmgsrnError(f"--image-size {args.image_size} is outside 16..2048")
    if not 1 <= args.spp <= 4096:
        raise ApmgsrnError(f"--spp {args.spp} is outside 1..4096")
    if importlib.util.find_spec("trame") is None or importlib.util.find_spec("trame_vuetify") is None:
        raise ApmgsrnError("the viewer needs the optional extra: pip install 'apmgsrn[viewer]'")

    from apmgsrn.device import resolve_device
    from apmgsrn.viewer.app import ViewerApp, ViewerAppConfig
    from apmgsrn.viewer.catalog import Catalog
    from apmgsrn.viewer.guard import is_loopback_name
    from apmgsrn.viewer.settings import ViewerConfig

    device = resolve_device(args.device)
    catalog = Catalog(args.path)
    port = args.port if args.port else _free_port(args.host)
    _check_port(args.host, port)
    size = args.image_size or (512 if device.type == "cuda" else 256)
    config = ViewerAppConfig(
        host=args.host,
        port=port,
        save_directory=Path(args.save_dir),
        viewer=ViewerConfig(
            image_width=size,
            image_height=size,
            samples_per_ray=args.spp,
            batch_size=(1 << 20) if device.type == "cuda" else (1 << 16),
            macro_cells=32 if device.type == "cuda" else 16,
        ),
    )
    if not is_loopback_name(args.host):
        print(
            f"warning: binding to {args.host}: anyone who can reach this machine on port {port} can open the "
            "page and render every file under PATH; prefer the default 127.0.0.1 and an SSH tunnel",
            file=sys.stderr,
        )
    app = ViewerApp(catalog, device, config)
    shown_host = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
    if ":" in shown_host:
        shown_host = f"[{shown_host}]"
    print(f"apmgsrn viewer: serving {catalog.root if catalog.single is None else catalog.root / catalog.single}")
    if app.skipped:
        print(f"not listed: {len(app.skipped)} file(s) under PATH (the page lists them too)")
        for skipped in app.skipped[:10]:
            print(f"  {skipped.name}: {skipped.reason}")
        if len(app.skipped) > 10:
            print(f"  and {len(app.skipped) - 10} more")
    print(f"open http://{shown_host}:{port}/   (Ctrl-C stops)", flush=True)
    try:
        app.serve()
    except KeyboardInterrupt:
        pass
    return 0


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def _check_port(host: str, port: int) -> None:
    """Fail with a clear message when the port is taken (the server would otherwise die in a traceback)."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, port))
    except OSError as exc:
        raise ApmgsrnError(f"cannot listen on {host}:{port} ({exc.strerror}); pick another --port") from None
