"""Job queues for brick training: Dask distributed (local cluster or a user's cluster) or this process.

Both queues look like :class:`concurrent.futures.Executor` to the coordinator: ``submit`` returns a
future with ``done()``, ``result()`` and ``exception()``. A job that raises is retried (``retries``
times); with Dask, a job whose worker dies is rescheduled on another worker by the scheduler. Dask is
imported only when a Dask queue is opened, never by ``import apmgsrn``.

Local clusters get one worker process per visible GPU, each pinned to its GPU by ``CUDA_VISIBLE_DEVICES``
set in the worker's environment before it starts (so torch in that process sees exactly one GPU), or
``workers`` CPU workers when there is no GPU.
"""

from __future__ import annotations

import concurrent.futures
import logging
import os
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from apmgsrn.arguments import check_int, check_optional_int
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.recipes import BRICKS


#: Resource name a cluster's workers may advertise (``--resources brick=1``) so that a worker with
#: several threads still trains one brick at a time.
BRICK_RESOURCE = "brick"


@dataclass(frozen=True)
class ExecutorConfig:
    """Where brick jobs run.

    Attributes:
        scheduler: ``tcp://host:port`` (any Dask address) or a scheduler JSON file of a running cluster;
            None: start a local cluster.
        workers: local workers; None: one per visible GPU, else one per CPU core up to
            ``BRICKS.cpu_workers`` (each brick on one core: small networks scale far better over
            bricks than over threads, and a multi-threaded step stalls when the cores are shared).
        retries: extra attempts of a job that raised (a job whose worker died is rescheduled anyway).
        processes: local workers as separate processes (False: threads of this process, for tests and
            notebooks; a crash then takes the coordinator down too).
        memory_limit: per local worker, bytes or a Dask size string (``"4GiB"``); None: the machine's
            memory divided by the workers.
        use_dask: False runs the jobs in threads of this process without Dask (also the fallback when
            Dask is not installed and no scheduler was given).
        dashboard: serve the local cluster's Dask dashboard on 127.0.0.1 (any free port); off by default.
    """

    scheduler: str | None = None
    workers: int | None = None
    retries: int = 2
    processes: bool = True
    memory_limit: int | str | None = None
    use_dask: bool = True
    dashboard: bool = False

    def __post_init__(self) -> None:
        check_optional_int("workers", self.workers, 1)
        check_int("retries", self.retries, 0)
        if self.scheduler is not None and self.workers is not None:
            raise InvalidArgument(
                f"workers={self.workers} starts local workers, but with scheduler={self.scheduler!r} the "
                "cluster's workers are used: drop one", arguments=("workers", "scheduler"),
            )


def visible_gpus() -> list[str]:
    """GPU ids this process may use, as ``CUDA_VISIBLE_DEVICES`` entries; empty without CUDA.

    Honours a ``CUDA_VISIBLE_DEVICES`` the user set; counting devices does not create a CUDA context.
    """
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if listed is not None:
        entries = [e.strip() for e in listed.split(",") if e.strip()]
        return entries[:count]
    return [str(i) for i in range(count)]


class JobQueue(ABC):
    """A queue of jobs with retries, ``concurrent.futures``-style.

    Attributes:
        workers: how many jobs can run at once (for the progress display).
        description: one line saying where jobs run.
        threads_per_job: torch CPU threads each job should use; None: decided on the worker.
    """

    workers: int = 1
    description: str = ""
    threads_per_job: int | None = None

    @abstractmethod
    def submit(self, fn: Callable[[Any], Any], argument: Any, key: str) -> Any:
        """Queue ``fn(argument)``; ``key`` names the job (unique within the queue). Returns a future."""

    @abstractmethod
    def wait(self, futures: Iterable[Any], timeout: float) -> set:
        """Block until at least one future is done or ``timeout`` seconds pass; returns the done ones."""

    @abstractmethod
    def running(self) -> int:
        """How many jobs are executing now (best effort)."""

    def close(self) -> None:
        """Release workers the queue started."""

    def __enter__(self) -> JobQueue:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class LocalJobQueue(JobQueue):
    """Jobs in threads of this process, retried on exceptions; needs no Dask.

    Args:
        workers: concurrent jobs.
        retries: extra attempts of a job that raised.
    """

    def __init__(self, workers: int = 1, retries: int = 2):
        self.workers = workers
        self.retries = retries
        self.description = f"{workers} thread(s) in this process"
        self.threads_per_job = max(1, (os.cpu_count() or 1) // workers)
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="brick")
        self._running: set[str] = set()
        self._lock = threading.Lock()

    def submit(self, fn, argument, key):
        return self._pool.submit(self._attempts, fn, argument, key)

    def _attempts(self, fn, argument, key):
        with self._lock:
            self._running.add(key)
        try:
            for attempt in range(self.retries + 1):
                try:
                    return fn(argument)
                except Exception:
                    if attempt == self.retries:
                        raise
                    logging.getLogger(__name__).warning("%s failed; retrying (%d of %d)", key, attempt + 1, self.retries)
        finally:
            with self._lock:
                self._running.discard(key)

    def wait(self, futures, timeout):
        return set(concurrent.futures.wait(list(futures), timeout, concurrent.futures.FIRST_COMPLETED).done)

    def running(self) -> int:
        with self._lock:
            return len(self._running)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskJobQueue(JobQueue):
    """Jobs on a Dask distributed cluster through a :class:`distributed.Client`.

    Args:
        client: a connected client.
        retries: extra attempts of a job that raised.
        owned: objects (cluster, client) to close with the queue.
        threads_per_job: torch CPU threads per job (None: decided on each worker).
    """

    def __init__(self, client, retries: int = 2, owned: tuple = (), threads_per_job: int | None = None):
        self.client = client
        self.retries = retries
        self._owned = owned
        self.threads_per_job = threads_per_job
        info = client.scheduler_info()
        workers = info.get("workers", {})
        self.workers = max(1, len(workers))
        # Use the brick resource only when every worker offers it: otherwise jobs would never start.
        self._resources = (
            {BRICK_RESOURCE: 1}
            if workers and all(BRICK_RESOURCE in (w.get("resources") or {}) for w in workers.values())
            else None
        )
        threads = sorted({int(w.get("nthreads", 1)) for w in workers.values()}) or [1]
        self.description = f"Dask cluster at {info.get('address', '?')}: {len(workers)} worker(s)"
        if threads != [1] and self._resources is None:
            self.description += (
                f" with {'/'.join(map(str, threads))} threads (each thread takes a brick; start workers "
                f"with --nthreads 1 or --resources {BRICK_RESOURCE}=1 for one brick per worker)"
            )

    def submit(self, fn, argument, key):
        return self.client.submit(fn, argument, key=key, retries=self.retries, pure=False, resources=self._resources)

    def wait(self, futures, timeout):
        from distributed import wait

        futures = list(futures)
        try:
            wait(futures, timeout=timeout, return_when="FIRST_COMPLETED")
        except TimeoutError:
            pass
        return {f for f in futures if f.done()}

    def running(self) -> int:
        try:
            processing = self.client.processing()
            info = self.client.scheduler_info().get("workers", {})
        except Exception:  # noqa: BLE001 - the display must never stop training
            return 0
        # A worker may hold a queued task beside the one it executes: count at most one per thread.
        return sum(min(len(keys), int(info.get(address, {}).get("nthreads", 1))) for address, keys in processing.items())

    def close(self) -> None:
        for resource in self._owned:
            try:
                resource.close()
            except Exception:  # noqa: BLE001 - shutting down a cluster must not mask the result
                pass


def open_job_queue(config: ExecutorConfig) -> JobQueue:
    """Start or join where the brick jobs run.

    Args:
        config: scheduler address/file, or local workers.

    Returns:
        A job queue; close it (or use it as a context manager) to stop workers it started.

    Raises:
        ApmgsrnError: Dask is not installed but a scheduler was given, the scheduler file is missing, or
            the cluster cannot be reached.
    """
    if not config.use_dask:
        return LocalJobQueue(config.workers or 1, config.retries)
    try:
        import distributed  # noqa: F401
    except ImportError:
        if config.scheduler:
            raise ApmgsrnError(
                f"scheduler={config.scheduler!r}: Dask is not installed; run `pip install apmgsrn[distributed]`",
                arguments=("scheduler",),
            ) from None
        return LocalJobQueue(config.workers or 1, config.retries)
    if config.scheduler:
        return _join_cluster(config)
    return _start_local_cluster(config)


def _join_cluster(config: ExecutorConfig) -> DaskJobQueue:
    from distributed import Client

    target = config.scheduler
    try:
        if "://" in target:
            client = Client(target, timeout="30s")
        else:
            path = Path(target).expanduser()
            if not path.is_file():
                raise ApmgsrnError(
                    f"{target}: no such scheduler file; pass the file the scheduler wrote "
                    "(dask scheduler --scheduler-file FILE) or an address like tcp://host:8786"
                )
            client = Client(scheduler_file=str(path), timeout="30s")
    except (OSError, TimeoutError) as exc:
        raise ApmgsrnError(f"scheduler={target!r}: cannot reach the Dask scheduler ({exc}); check that it runs",
                           arguments=("scheduler",)) from None
    return DaskJobQueue(client, config.retries, owned=(client,))


def _local_security():
    """TLS with a fresh throw-away certificate for a local process cluster, so that no other local user's
    client can reach its scheduler or workers (Dask refuses a connection without the certificate).

    Returns:
        ``(protocol, Security)``: ``"tls://"`` and the credentials, or ``"inproc://"`` and None for a cluster
        of threads in this process (unreachable from outside it).
    """
    from distributed.security import Security

    try:
        return "tls://", Security.temporary()
    except ImportError:
        raise ApmgsrnError(
            "a local Dask cluster needs the 'cryptography' package for its TLS credentials; run "
            "`pip install apmgsrn[distributed]`"
        ) from None


def _start_local_cluster(config: ExecutorConfig) -> DaskJobQueue:
    import psutil
    from distributed import Client, LocalCluster, Nanny, Scheduler, SpecCluster

    gpus = visible_gpus() if config.processes else []
    cores = os.cpu_count() or 1
    workers = config.workers or (len(gpus) if gpus else max(1, min(cores, BRICKS.cpu_workers)))
    threads_per_job = max(1, cores // workers)
    memory_limit = config.memory_limit or int(psutil.virtual_memory().total // workers)
    # Loopback only, TLS between scheduler, workers and this client, dashboard only when asked for.
    protocol, security = _local_security() if config.processes else ("inproc://", None)
    dashboard = "127.0.0.1:0" if config.dashboard else None
    if gpus:
        # One process per worker, each seeing one GPU (round robin when there are more workers than GPUs).
        specs = {
            f"gpu-{i}": {
                "cls": Nanny,
                "options": {
                    "nthreads": 1,
                    "memory_limit": memory_limit,
                    "env": {"CUDA_VISIBLE_DEVICES": gpus[i % len(gpus)]},
                    "host": "127.0.0.1",
                    "protocol": protocol,
                    "security": security,
                },
            }
            for i in range(workers)
        }
        cluster = SpecCluster(
            workers=specs,
            scheduler={"cls": Scheduler, "options": {"dashboard_address": dashboard, "host": "127.0.0.1",
                                                     "protocol": protocol, "security": security}},
            security=security,
            silence_logs=logging.ERROR,
        )
        where = f"local Dask cluster: {workers} worker(s) on GPU(s) {','.join(gpus)}"
    else:
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=config.processes,
            memory_limit=memory_limit,
            host="127.0.0.1" if config.processes else None,
            protocol=protocol,
            security=security,
            dashboard_address=dashboard,
            silence_logs=logging.ERROR,
        )
        kind = "processes" if config.processes else "threads"
        where = f"local Dask cluster: {workers} CPU worker {kind}, {threads_per_job} torch thread(s) each"
    client = Client(cluster, security=security)
    queue = DaskJobQueue(client, config.retries, owned=(client, cluster), threads_per_job=threads_per_job)
    queue.description = where
    if config.dashboard:
        queue.description += f"; dashboard {cluster.dashboard_link}"
    return queue
