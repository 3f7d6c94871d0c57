"""``apmgsrn view`` argument handling and import hygiene (the server itself: test_viewer_browser.py)."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest
from viewer_data import make_viewer_folder

from apmgsrn.cli.main import build_parser, main


def _fails(capsys, argv, fragment):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and fragment in err and "Traceback" not in err


def test_defaults_bind_to_loopback():
    args = build_parser().parse_args(["view"])
    assert args.host == "127.0.0.1" and args.path == "." and args.port == 8080
    pytest.importorskip("msgpack", reason="needs the [viewer] extra")
    from apmgsrn.viewer.guard import is_loopback_name

    assert is_loopback_name("127.0.0.1") and is_loopback_name("localhost") and is_loopback_name("::1")
    assert not is_loopback_name("0.0.0.0") and not is_loopback_name("192.168.1.5")
    assert not is_loopback_name("localhost.evil.example") and not is_loopback_name("")


def test_user_errors_are_one_line(tmp_path, capsys):
    folder = make_viewer_folder(tmp_path)
    _fails(capsys, ["view", str(tmp_path / "missing")], "no such file")
    _fails(capsys, ["view", str(folder / "notes.txt")], "neither a model")
    _fails(capsys, ["view", str(folder), "--port", "70000"], "--port")
    _fails(capsys, ["view", str(folder), "--spp", "0"], "--spp")
    _fails(capsys, ["view", str(folder), "--device", "tpu"], "device")


def test_a_taken_port_is_a_user_error(tmp_path, capsys):
    folder = make_viewer_folder(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        _fails(capsys, ["view", str(folder), "--port", str(port)], "cannot listen")


def test_importing_the_package_and_cli_loads_no_web_stack():
    code = (
        "import sys, apmgsrn, apmgsrn.viewer, apmgsrn.viewer.session, apmgsrn.viewer.catalog;"
        "from apmgsrn.cli.main import build_parser; build_parser();"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('trame', 'trame_server', 'playwright', 'aiohttp')];"
        "assert not bad, bad;"
        "import torch; assert not torch.cuda.is_initialized()"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.parametrize("extra", [["--image-size", "8"]])
def test_image_size_limits(tmp_path, capsys, extra):
    folder = make_viewer_folder(tmp_path)
    _fails(capsys, ["view", str(folder), *extra], "--image-size")
