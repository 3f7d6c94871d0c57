"""``apmgsrn view`` in a subprocess on a free loopback port, and a raw wslink client to probe it with.

The client speaks what the trame page speaks (msgpack messages in chunks of a 12-byte header: message id,
offset, total size; uint32 little endian) over aiohttp, so tests can send what no page would.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import struct
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass
class ViewerProcess:
    url: str
    port: int
    process: subprocess.Popen
    log: Path

    def log_text(self) -> str:
        return self.log.read_text(errors="replace")

    def rss_mib(self) -> float:
        """Resident memory of the server process (MiB)."""
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
        raise RuntimeError("no VmRSS")


@contextlib.contextmanager
def running_viewer(folder: Path, scratch: Path, *extra: str, env: dict | None = None):
    """Serve ``folder`` with ``apmgsrn view`` until the block ends (then Ctrl-C, as a user stops it)."""
    port = free_port()
    log = scratch / f"server-{port}.log"
    with open(log, "w") as out:
        process = subprocess.Popen(
            [sys.executable, "-m", "apmgsrn", "view", str(folder), "--port", str(port), "--device", "cpu",
             "--image-size", "64", "--spp", "32", *extra],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
    viewer = ViewerProcess(f"http://127.0.0.1:{port}/", port, process, log)
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                urllib.request.urlopen(viewer.url, timeout=2).read()
                break
            except OSError:
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"viewer did not start:\n{viewer.log_text()}") from None
                time.sleep(0.2)
        yield viewer
    finally:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def chunk(payload: bytes, identifier: int = 1, declared: int | None = None) -> bytes:
    """One wslink chunk carrying all of ``payload`` (``declared``: the total size its header claims)."""
    return struct.pack("<III", identifier, 0, len(payload) if declared is None else declared) + payload


class WslinkClient:
    """A websocket client of the viewer that speaks wslink by hand (use ``async with``)."""

    def __init__(self, url: str, origin: str | None = None, host: str | None = None) -> None:
        self.url = url
        self.headers = {k: v for k, v in (("Origin", origin), ("Host", host)) if v is not None}
        self.published: list[dict] = []  # what the server pushed to this client (state updates)
        self._count = 0
        self._client_id = "c0"

    async def __aenter__(self) -> "WslinkClient":
        import aiohttp

        self.http = aiohttp.ClientSession()
        socket_url = self.url.replace("http://", "ws://") + "ws"
        try:
            self.socket = await self.http.ws_connect(
                socket_url, headers=self.headers, max_msg_size=0, autoclose=False
            )
        except BaseException:
            await self.http.close()
            raise
        return self

    async def __aexit__(self, *_) -> None:
        await self.socket.close()
        await self.http.close()

    async def page_session(self) -> dict:
        """What the page gets when it asks for its session (websocket address and secret)."""
        async with self.http.post(self.url + "paraview/", json={}) as response:
            response.raise_for_status()
            return await response.json()

    async def send(self, message: dict) -> None:
        import msgpack

        await self.socket.send_bytes(chunk(msgpack.packb(message), identifier=self._count + 1))

    async def request(self, method: str, args: list, system: bool = False) -> dict:
        """Send an RPC and return the server's reply to it (publishes in between go to ``published``)."""
        self._count += 1
        identifier = f"system:c0:{self._count}" if system else f"rpc:{self._client_id}:{self._count}"
        await self.send({"wslink": "1.0", "id": identifier, "method": method, "args": args, "kwargs": {}})
        while True:
            message = await self.receive()
            if message.get("id") == identifier:
                return message

    async def hello(self, secret: str) -> dict:
        reply = await self.request("wslink.hello", [{"secret": secret}], system=True)
        if "result" in reply:
            self._client_id = reply["result"]["clientID"]
        return reply

    async def receive(self, timeout: float = 30.0) -> dict:
        """The next whole message from the server (a state publish is also kept in ``published``)."""
        import aiohttp
        from wslink.chunking import UnChunker

        unchunker = UnChunker()
        unchunker.set_max_message_size(1 << 30)  # the server is trusted here
        while True:
            frame = await self.socket.receive(timeout=timeout)
            if frame.type != aiohttp.WSMsgType.BINARY:
                raise ConnectionError(f"connection ended: {frame.type.name} {frame.data} {frame.extra}")
            message = unchunker.process_chunk(frame.data)
            if message is not None:
                if str(message.get("id", "")).startswith("publish:"):
                    self.published.append(message.get("result") or {})
                return message

    async def drain(self, quiet: float = 0.5, limit: float = 30.0) -> None:
        """Receive until the server has been quiet for ``quiet`` seconds (at most ``limit`` seconds)."""
        end = time.monotonic() + limit
        while time.monotonic() < end:
            try:
                await self.receive(timeout=quiet)
            except asyncio.TimeoutError:
                return

    async def closed_by_server(self, timeout: float = 10.0):
        """Wait until the server closes the connection; return its close code (None if it stayed open)."""
        import aiohttp

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                frame = await self.socket.receive(timeout=max(0.1, end - time.monotonic()))
            except asyncio.TimeoutError:
                return None
            if frame.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSING, aiohttp.WSMsgType.CLOSED):
                return self.socket.close_code if frame.type != aiohttp.WSMsgType.CLOSE else frame.data
        return None


def run(coroutine):
    """Run a probe coroutine to completion."""
    return asyncio.run(coroutine)
