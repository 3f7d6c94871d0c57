"""CPU threads that survive contention: how long an idle OpenMP thread spins, and how many threads a loop uses.

On a machine where other processes use some of the cores (a laptop, a login node, CI, a shared workstation),
a multi-threaded step waits at each OpenMP barrier for a thread that the kernel has put behind another
process. Two measures, both here so that training, decoding, evaluation and rendering share them:

1. **Spin briefly, then sleep.** libgomp (PyTorch's OpenMP runtime on Linux) lets a thread that waits for
   the next parallel region spin 300,000 rounds before it sleeps, about 10 ms on the 2-core development
   machine (37 ns per ``pause``). A spinning thread keeps its core busy, so the thread it waits for, queued
   behind another process on the other core, cannot move there. Measured with other jobs on both cores
   (docs/benchmarks_contention.md): 300 training iterations took 3-4x longer with the default spin and
   two threads than with this module's settings. :func:`set_openmp_wait_policy` makes
   ``RUNTIME.spin_count`` (:mod:`apmgsrn.recipes`) the default; it runs
   on ``import apmgsrn`` (libgomp reads its settings once, when torch loads it, so it has an effect only
   when apmgsrn is imported before torch, as the command line and a fresh script do).
2. **Measure, keep the fastest.** :class:`ThreadGovernor` times a loop's work units (training iterations,
   decoding batches, ray-marching rounds) under each thread count worth trying (all cores, half of
   them, one), keeps the fastest, and tries the others again now and then, waiting twice as long each
   time the choice stands. When a core is busy the loop runs at the speed of the cores that are free,
   not at the speed of the slowest thread.

And where work comes in independent pieces that release the GIL (the LZMA coding of a packed file's
parameters), :func:`map_in_threads` runs them side by side on as many Python threads as the process may use
(:func:`work_threads`: torch's count, so a process told to use one core keeps to one; a series' quantisation-aware
fine-tune runs its steps so too, :func:`apmgsrn.series.qat.qat_lanes`).

Importing this module does not import torch (``import apmgsrn`` stays light); the governor imports it
when used.
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from apmgsrn.recipes import RUNTIME

Item, Result = TypeVar("Item"), TypeVar("Result")

#: Settings by which a user chooses the wait policy; when any is set, theirs stands.
WAIT_POLICY_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def set_openmp_wait_policy() -> bool:
    """Make ``RUNTIME.spin_count`` libgomp's spin count (``GOMP_SPINCOUNT``), unless torch is loaded or the user
    chose one: about 0.1 ms, enough to bridge the gaps between the operations of one step, short enough to hand
    the core back when another process needs it.

    Returns:
        True when the setting was made (it then applies to this process and the processes it starts).
    """
    if "torch" in sys.modules or any(name in os.environ for name in WAIT_POLICY_VARIABLES):
        return False
    os.environ["GOMP_SPINCOUNT"] = str(RUNTIME.spin_count)
    return True


def work_threads() -> int:
    """Threads a process may keep busy: torch's thread count where torch is loaded (so a process told to use
    one core, ``OMP_NUM_THREADS=1`` or ``torch.set_num_threads(1)``, keeps to one), else one."""
    torch = sys.modules.get("torch")
    return max(1, int(torch.get_num_threads())) if torch is not None else 1


def map_in_threads(function: Callable[[Item], Result], items: Iterable[Item], threads: int | None = None
                   ) -> list[Result]:
    """``[function(item) for item in items]`` on up to ``threads`` Python threads (None: :func:`work_threads`),
    the results in the items' order: for work that releases the GIL (LZMA, NumPy on large arrays), which then
    runs on that many cores at once. One thread, or one item: a plain loop. An error in any item is raised."""
    items = list(items)
    workers = min(threads if threads is not None else work_threads(), len(items))
    if workers <= 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(function, items))


def thread_candidates(threads: int) -> tuple[int, ...]:
    """Thread counts worth timing for a loop that may use ``threads``: all, half, one (most first)."""
    threads = max(1, int(threads))
    return tuple(sorted({threads, max(1, threads // 2), 1}, reverse=True))


class ThreadGovernor:
    """Chooses torch's CPU thread count for a loop of alike work units by timing them.

    Use it as a context manager around the loop and call :meth:`tick` after every unit; leaving the
    context restores the calling thread's thread count. The choice and the timings persist from one
    ``with`` to the next, so an object that renders frame after frame keeps what it learned.

    Probing: each candidate runs for at least ``probe_units`` units and ``probe_seconds`` (the first unit
    after a switch is not timed); the one with the lowest median time per unit of work is kept, the
    fewest threads among those within ``tolerance`` of it. It is kept for ``hold_seconds``, then all are
    timed again; every time the choice stands the hold doubles, up to ``max_hold_seconds``.

    Args:
        threads: most threads to use (None: torch's current count when the context is entered).
        enabled: False makes it do nothing (a GPU loop, or numbers that depend on the thread count).
        probe_units: fewest units timed per candidate.
        probe_seconds: least time spent per candidate.
        hold_seconds: first time the choice is kept before the next probe.
        max_hold_seconds: longest time between probes.
        tolerance: relative margin within which fewer threads are preferred.
        clock: time source (tests pass their own).
    """

    def __init__(
        self,
        threads: int | None = None,
        enabled: bool = True,
        probe_units: int = 3,
        probe_seconds: float = 0.1,
        hold_seconds: float = 2.0,
        max_hold_seconds: float = 60.0,
        tolerance: float = 0.03,
        clock: Callable[[], float] = time.perf_counter,
    ):
        self.max_threads = threads
        self.enabled = enabled
        self.probe_units = probe_units
        self.probe_seconds = probe_seconds
        self.base_hold = hold_seconds
        self.max_hold = max_hold_seconds
        self.tolerance = tolerance
        self.clock = clock
        self.threads: int | None = None  # the count in use (None before the first probe)
        self.history: list[tuple[int, dict[int, float]]] = []  # (choice, median time per unit) of each probe
        self._candidates: tuple[int, ...] = ()
        self._probing: list[int] = []  # candidates still to time in the current probe
        self._results: dict[int, float] = {}
        self._times: list[float] = []
        self._spent = 0.0
        self._mark: float | None = None
        self._hold = hold_seconds
        self._hold_until = 0.0
        self._saved: int | None = None
        self._depth = 0

    # ------------------------------------------------------------------ context
    def __enter__(self) -> ThreadGovernor:
        self._depth += 1
        if not self.enabled or self._depth > 1:
            return self
        import torch

        self._saved = torch.get_num_threads()
        candidates = thread_candidates(self.max_threads or self._saved)
        if candidates != self._candidates:
            self._candidates = candidates
            self.threads = None
        if len(candidates) == 1:
            self._set(candidates[0])
        elif self.threads is None or self.clock() >= self._hold_until:
            self._start_probe()
        else:
            self._set(self.threads)
        self._mark = None
        return self

    def __exit__(self, *exc) -> None:
        self._depth -= 1
        if not self.enabled or self._depth > 0:
            return
        import torch

        if self._saved is not None and torch.get_num_threads() != self._saved:
            torch.set_num_threads(self._saved)

    # ------------------------------------------------------------------ loop
    def tick(self, work: float = 1.0) -> None:
        """One work unit is done.

        Args:
            work: its size in any unit (points, samples), so that units of unequal size compare; 1 when
                the units are alike.
        """
        if not self.enabled or len(self._candidates) < 2:
            return
        now = self.clock()
        if self._mark is None:  # the unit after a switch or an entry warms up: not timed
            self._mark = now
            return
        elapsed, self._mark = now - self._mark, now
        if not self._probing:
            if now >= self._hold_until:
                self._start_probe()
            return
        self._times.append(elapsed / max(work, 1e-12))
        self._spent += elapsed
        if len(self._times) >= self.probe_units and self._spent >= self.probe_seconds:
            self._results[self._probing.pop(0)] = statistics.median(self._times)
            if self._probing:
                self._switch(self._probing[0])
            else:
                self._decide(now)

    # ------------------------------------------------------------------ internals
    def _start_probe(self) -> None:
        # The current choice first (no switch needed), then the others, most threads first.
        order = [c for c in self._candidates if c == self.threads] + [c for c in self._candidates if c != self.threads]
        self._probing, self._results = order, {}
        self._switch(order[0])

    def _switch(self, threads: int) -> None:
        self._set(threads)
        self._times, self._spent, self._mark = [], 0.0, None

    def _set(self, threads: int) -> None:
        import torch

        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
        self.threads = threads

    def _decide(self, now: float) -> None:
        fastest = min(self._results.values())
        choice = min(c for c, t in self._results.items() if t <= fastest * (1 + self.tolerance))
        previous = self.history[-1][0] if self.history else None
        self._hold = min(self.max_hold, self._hold * 2) if choice == previous else self.base_hold
        self.history.append((choice, dict(self._results)))
        self._hold_until = now + self._hold
        self._set(choice)
        self._mark = None


#: The governor of inference loops (decode, eval, render): one per process, so what it learns carries over
#: from one slab, evaluation or frame to the next. Loops on a GPU use :data:`NO_GOVERNOR`.
INFERENCE_THREADS = ThreadGovernor()
#: A governor that does nothing (GPU loops).
NO_GOVERNOR = ThreadGovernor(enabled=False)


def inference_governor(device_type: str) -> ThreadGovernor:
    """:data:`INFERENCE_THREADS` for a loop on the CPU, :data:`NO_GOVERNOR` elsewhere.

    Args:
        device_type: ``torch.device.type`` of the loop's tensors.
    """
    return INFERENCE_THREADS if device_type == "cpu" else NO_GOVERNOR
