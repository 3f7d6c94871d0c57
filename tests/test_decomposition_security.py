"""The local Dask cluster that `train --bricks` starts is closed to everyone but its own client."""

from __future__ import annotations

import urllib.error
import urllib.request

import pytest

pytest.importorskip("distributed")

from distributed import Client  # noqa: E402

from apmgsrn.decomposition.executor import ExecutorConfig, open_job_queue  # noqa: E402


def _increment(value: int) -> int:
    return value + 1


def _status(port: int, path: str) -> int:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as response:
            return response.status
    except urllib.error.HTTPError as error:
        return error.code


def test_local_cluster_is_loopback_tls_without_dashboard_and_refuses_other_clients():
    with open_job_queue(ExecutorConfig(workers=1)) as queue:
        address = queue.client.scheduler.address
        assert address.startswith("tls://127.0.0.1:")
        workers = queue.client.scheduler_info()["workers"]
        assert workers and all(w.startswith("tls://127.0.0.1:") for w in workers)
        # A probe on the same machine without the cluster's certificate: plain TCP and TLS both fail.
        for target in (address.replace("tls://", "tcp://"), address):
            with pytest.raises(Exception):  # noqa: B017 - refused in transport or handshake, either way
                Client(target, timeout="5s")
        # No dashboard unless asked: the scheduler's HTTP port answers health checks only.
        port = queue.client.scheduler_info()["services"]["dashboard"]
        assert _status(port, "/status") == 404
        assert queue.submit(_increment, 41, key="answer").result() == 42  # its own client still works


def test_the_dashboard_is_served_on_loopback_when_asked_for():
    with open_job_queue(ExecutorConfig(workers=1, dashboard=True)) as queue:
        assert "dashboard http://127.0.0.1:" in queue.description
        port = queue.client.scheduler_info()["services"]["dashboard"]
        assert _status(port, "/status") == 200
