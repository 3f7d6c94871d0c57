"""Hostile clients of a running ``apmgsrn view`` (issue 11, item 10), probed with a raw websocket client on
loopback: a 13-byte frame declaring a 1 GiB message, a client without the secret, a page of another
origin or a rebound DNS name, a page writing state that is the server's, uploads left on disk. The
server runs in its own process so its resident memory can be measured."""

from __future__ import annotations

import json
import socket
import urllib.error
import urllib.request

import pytest
from viewer_data import make_viewer_folder
from viewer_server import WslinkClient, chunk, run, running_viewer

pytest.importorskip("trame", reason="needs the [viewer] extra")
pytest.importorskip("aiohttp", reason="needs the [viewer] extra (trame brings aiohttp)")

AUTHENTICATION_ERROR = -32000  # wslink's code for "not authenticated"
METHOD_NOT_FOUND = -32601
MESSAGE_TOO_BIG = 1009


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    scratch = tmp_path_factory.mktemp("hostile_clients")
    (scratch / "tmp").mkdir()
    folder = make_viewer_folder(scratch)
    # TMPDIR of its own: whatever the viewer leaves in a temporary folder shows up there.
    with running_viewer(folder, scratch, env={"TMPDIR": str(scratch / "tmp")}) as server:
        server.scratch = scratch
        yield server


def _status(url: str, host: str | None = None, method: str = "GET") -> int:
    request = urllib.request.Request(url, method=method, headers={"Host": host} if host else {})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status
    except urllib.error.HTTPError as error:
        return error.code


async def _authenticated(viewer) -> WslinkClient:
    client = WslinkClient(viewer.url)
    await client.__aenter__()
    session = await client.page_session()
    reply = await client.hello(session["secret"])
    assert "result" in reply, reply
    return client


# ------------------------------------------------------------------------------------------ binding
def test_the_server_listens_on_loopback_only(viewer):
    listening = []
    for table in ("tcp", "tcp6"):
        for line in open(f"/proc/{viewer.process.pid}/net/{table}").read().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            address, port = local.split(":")
            if int(port, 16) == viewer.port and state == "0A":  # 0A: LISTEN
                listening.append(address)
    assert listening and all(address in ("0100007F", "00000000000000000000000001000000") for address in listening)
    # The machine's other addresses do not answer.
    outside = [info[4][0] for info in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)]
    for address in {a for a in outside if not a.startswith("127.")}:
        with pytest.raises(OSError):
            socket.create_connection((address, viewer.port), timeout=2).close()


# ------------------------------------------------------------------------------------------ secret
def test_a_client_without_the_secret_cannot_call_the_app(viewer):
    async def probe():
        async with WslinkClient(viewer.url) as client:
            reply = await client.hello("wslink-secret")  # wslink's default secret
            assert reply["error"]["code"] == AUTHENTICATION_ERROR
            for method, args in (
                ("trame.trigger", ["viewer_open", ["tiny.apmgsrn"], {}]),
                ("trame.state.update", [[{"key": "source_name", "value": "tiny.apmgsrn"}]]),
                ("trame.state.get", []),
            ):
                reply = await client.request(method, args)
                assert reply["error"]["code"] == AUTHENTICATION_ERROR, method
        # The page's secret is new in every run: 256 random bits, not the default.
        async with WslinkClient(viewer.url) as client:
            secret = (await client.page_session())["secret"]
            assert secret != "wslink-secret" and len(secret) >= 40
            assert "result" in await client.hello(secret)
            state = (await client.request("trame.state.get", []))["result"]["state"]
            assert state["source_name"] != "tiny.apmgsrn"  # the refused calls changed nothing

    run(probe())


# ------------------------------------------------------------------------------------------ memory
def test_a_frame_declaring_a_gigabyte_is_refused_without_the_memory(viewer):
    async def probe():
        for authenticated in (False, True):
            client = await _authenticated(viewer) if authenticated else WslinkClient(viewer.url)
            if not authenticated:
                await client.__aenter__()
            try:
                before = viewer.rss_mib()
                await client.socket.send_bytes(chunk(b"x", declared=1 << 30))  # 13 bytes
                assert await client.closed_by_server() == MESSAGE_TOO_BIG
                assert viewer.rss_mib() - before < 64, (before, viewer.rss_mib())
            finally:
                await client.__aexit__()
        # Many messages in flight, each declaring the most a message may have: refused as well.
        client = await _authenticated(viewer)
        try:
            before = viewer.rss_mib()
            for identifier in range(1, 9):
                if client.socket.closed:
                    break
                await client.socket.send_bytes(chunk(b"x", identifier=identifier, declared=(1 << 20) + 1000))
            assert await client.closed_by_server() == MESSAGE_TOO_BIG
            assert viewer.rss_mib() - before < 64
        finally:
            await client.__aexit__()
        # The server serves on.
        client = await _authenticated(viewer)
        await client.__aexit__()

    run(probe())
    assert viewer.process.poll() is None


# ------------------------------------------------------------------------------------------ origin
def test_a_foreign_host_or_origin_is_refused(viewer):
    rebound = f"attacker.example:{viewer.port}"  # a DNS name rebound to 127.0.0.1 by a foreign page
    assert _status(viewer.url) == 200
    assert _status(viewer.url, host=f"localhost:{viewer.port}") == 200
    assert _status(viewer.url, host=rebound) == 403
    assert _status(viewer.url + "paraview/", host=rebound, method="POST") == 403
    assert _status(viewer.url, host="[::1") == 403  # a Host that does not parse is refused, not a crash

    async def probe():
        import aiohttp

        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            async with WslinkClient(viewer.url, origin="http://attacker.example"):
                pass
        assert refused.value.status == 403
        for origin in ("null", "http://[bad"):
            with pytest.raises(aiohttp.WSServerHandshakeError):
                async with WslinkClient(viewer.url, origin=origin):
                    pass
        async with WslinkClient(viewer.url, origin=f"http://127.0.0.1:{viewer.port}") as client:
            assert "result" in await client.hello((await client.page_session())["secret"])

    run(probe())


# ------------------------------------------------------------------------------------------ state
def test_a_page_cannot_write_the_servers_state(viewer):
    injected = {
        "entries": [{"title": "evil", "value": "../secret.npy"}],
        "trame__template_main": "<div>{{ constructor.constructor('alert(1)')() }}</div>",
        "error_message": "your session expired: log in at http://attacker.example",
        "source_name": "../secret.npy",
        "colormap": "../../etc/passwd.json",
        "samples_per_ray": 10**9,
        "frame_src": "http://attacker.example/track.png",
    }

    async def probe():
        listener = await _authenticated(viewer)  # a page already open
        attacker = await _authenticated(viewer)
        try:
            listing = (await attacker.request("trame.state.get", []))["result"]["state"]["entries"]
            changes = [{"key": key, "value": value} for key, value in injected.items()]
            reply = await attacker.request("trame.state.update", [changes])
            assert "error" not in reply
            odd = [{"key": "source_name", "value": [1]}, {"key": ["x"], "value": 1}, "entries", None]
            assert "error" not in await attacker.request("trame.state.update", [odd])
            for method in ("application.exit", "application.exit.later"):
                assert (await attacker.request(method, []))["error"]["code"] == METHOD_NOT_FOUND
            await attacker.request("trame.lifecycle.update", ["server_ready"])  # only client_* events pass
            # A page opening later gets the server's state.
            later = await _authenticated(viewer)
            state = (await later.request("trame.state.get", []))["result"]["state"]
            await later.__aexit__()
            assert state["entries"] == listing
            for key, value in injected.items():
                assert state.get(key) != value, key
            # The page already open never saw the injected values.
            await listener.drain()
            # It did hear the server: the refused keys were sent back to every page with the server's values.
            assert any(update.get("entries") == listing for update in listener.published)
            seen = json.dumps(listener.published)
            assert "attacker.example" not in seen and "constructor" not in seen and "evil" not in seen
        finally:
            await attacker.__aexit__()
            await listener.__aexit__()

    run(probe())
    assert viewer.process.poll() is None


# ------------------------------------------------------------------------------------------ uploads
def test_uploads_leave_nothing_on_disk(viewer):
    preset = json.dumps([{"Name": "Greens", "RGBPoints": [0, 0, 0.2, 0, 1, 0.4, 1, 0.4]}])

    async def probe():
        client = await _authenticated(viewer)
        try:
            await client.request("trame.trigger", ["viewer_upload_preset", ["upload_me.json", preset], {}])
            await client.request("trame.trigger", ["viewer_upload_preset", ["bad.json", "[" * 100_000], {}])
            await client.request("trame.trigger", ["viewer_upload_preset", ["run.py", "import os"], {}])
            state = (await client.request("trame.state.get", []))["result"]["state"]
            assert "Greens (uploaded upload_me.json)" in state["colormaps"]
            assert state["error_message"].startswith("run.py: upload a ParaView colour-map preset")
            # Past the cap (the upload limit and a margin): the connection closes; nothing is kept.
            await client.socket.send_bytes(chunk(b"x" * (2 << 20)))
            assert await client.closed_by_server() == MESSAGE_TOO_BIG
        finally:
            await client.__aexit__()

    run(probe())
    assert sorted(p.name for p in (viewer.scratch / "tmp").iterdir() if "apmgsrn" in p.name) == []
