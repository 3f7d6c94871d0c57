"""Threads that survive contention (apmgsrn/threads.py): the governor's choices, the OpenMP wait policy,
and that a training run whose thread count changes mid-run gives the same model as one that never does."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.recipes import RUNTIME
from apmgsrn.threads import ThreadGovernor, thread_candidates
from apmgsrn.training.trainer import Trainer, TrainConfig


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def run_units(governor: ThreadGovernor, clock: FakeClock, seconds_per_unit: dict[int, float], units: int) -> list[int]:
    """Tick ``units`` work units, each taking the time its thread count is given; returns the count per unit."""
    used = []
    for _ in range(units):
        used.append(torch.get_num_threads())
        clock.now += seconds_per_unit[torch.get_num_threads()]
        governor.tick()
    return used


def test_candidates_are_all_half_and_one():
    assert thread_candidates(8) == (8, 4, 1)
    assert thread_candidates(2) == (2, 1)
    assert thread_candidates(1) == (1,)
    assert thread_candidates(0) == (1,)


def test_governor_keeps_the_faster_count_and_restores_the_callers():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        clock = FakeClock()
        governor = ThreadGovernor(clock=clock, probe_units=3, probe_seconds=0.0, hold_seconds=10.0)
        with governor:
            used = run_units(governor, clock, {2: 0.030, 1: 0.020}, 40)  # a busy core: one thread wins
        assert governor.history[0][0] == 1
        assert used[-1] == 1 and 2 in used  # both were tried, one kept
        assert torch.get_num_threads() == 2  # the caller's count is back
        with governor:  # the choice persists into the next loop while it holds
            assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_governor_prefers_fewer_threads_only_within_the_tolerance_and_reprobes_after_the_hold():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        clock = FakeClock()
        governor = ThreadGovernor(clock=clock, probe_units=2, probe_seconds=0.0, hold_seconds=1.0,
                                  max_hold_seconds=4.0, tolerance=0.05)
        with governor:
            run_units(governor, clock, {2: 0.010, 1: 0.0104}, 20)  # within 5 %: one thread
            assert governor.history[0][0] == 1
            run_units(governor, clock, {2: 0.010, 1: 0.020}, 400)  # the core came back: two threads
            assert governor.history[-1][0] == 2
            choices = [choice for choice, _ in governor.history]
            run_units(governor, clock, {2: 0.010, 1: 0.020}, 2000)
            probes_late = len(governor.history) - len(choices)
        # 20 s of units at a hold doubling to 4 s: a handful of probes, not one per second
        assert 2 <= probes_late <= 8
    finally:
        torch.set_num_threads(before)


def test_disabled_governor_touches_nothing():
    before = torch.get_num_threads()
    governor = ThreadGovernor(enabled=False, threads=1)
    with governor:
        governor.tick()
        assert torch.get_num_threads() == before
    assert governor.history == []


def _trainer(volume: torch.Tensor, governor: ThreadGovernor) -> Trainer:
    config = preset_config("apmgsrn", "small")
    field = NeuralField(config, generator=torch.Generator().manual_seed(0))
    trainer = Trainer(field, volume, TrainConfig(iterations=40, batch_size=4096, seed=3))
    trainer.thread_governor = governor
    return trainer


def test_training_gives_the_same_model_when_the_thread_count_changes_mid_run(test_data):
    """The governor may switch threads at any iteration: the model must not notice (exact resume,
    reproducible runs). Here it switches every few iterations, against a run fixed on two threads."""
    raw = np.fromfile(test_data / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    volume = torch.from_numpy(raw.astype(np.float32) / 255.0)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        fixed = _trainer(volume, ThreadGovernor(enabled=False))
        if not fixed._thread_invariant():
            pytest.skip("this CPU's kernels give other numbers on other thread counts: the governor stays off")
        fixed.run()
        switching = _trainer(volume, ThreadGovernor(probe_units=1, probe_seconds=0.0, hold_seconds=0.0,
                                                    max_hold_seconds=0.0))
        switching.run()
    finally:
        torch.set_num_threads(before)
    probes = switching.thread_governor.history
    assert len(probes) >= 4 and all(set(timed) == {1, 2} for _, timed in probes)  # ran on both, many times
    for (name, a), (_, b) in zip(fixed.field.state_dict().items(), switching.field.state_dict().items()):
        assert torch.equal(a, b), name


def test_a_step_whose_numbers_follow_the_thread_count_keeps_the_governor_off(test_data, monkeypatch):
    """The rule of thumb (small batch, float32, an invariant encoder) is checked by running the step on each
    thread count: a model whose output moves with the thread count (as matrix products do on some CPUs)
    must not have its threads switched mid-run."""
    from apmgsrn.training import trainer as trainer_module

    raw = np.fromfile(test_data / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    volume = torch.from_numpy(raw.astype(np.float32) / 255.0)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        monkeypatch.setattr(trainer_module, "_THREAD_PROBES", {})
        steady = _trainer(volume, ThreadGovernor())
        if not steady._thread_invariant():
            pytest.skip("this CPU's kernels give other numbers on other thread counts (the probe's own finding)")
        original = NeuralField.normalized

        def thread_dependent(self, points, *args, **kwargs):
            return original(self, points, *args, **kwargs) * (1 + 1e-6 * torch.get_num_threads())

        monkeypatch.setattr(NeuralField, "normalized", thread_dependent)
        monkeypatch.setattr(trainer_module, "_THREAD_PROBES", {})
        drifting = _trainer(volume, ThreadGovernor())
        assert not drifting._thread_invariant()
        field = NeuralField(preset_config("apmgsrn", "small"), generator=torch.Generator().manual_seed(0))
        assert not Trainer(field, volume, TrainConfig(iterations=4, batch_size=4096)).thread_governor.enabled
    finally:
        torch.set_num_threads(before)


def test_trainer_keeps_its_threads_where_they_would_change_the_numbers():
    volume = torch.zeros(8, 8, 8)
    config = preset_config("apmgsrn", "small")
    field = NeuralField(config, generator=torch.Generator().manual_seed(0))
    big_batch = Trainer(field, volume, TrainConfig(iterations=1, batch_size=65536))
    assert not big_batch.thread_governor.enabled  # ATen would sum the loss in per-thread parts


def _spin_count_in_fresh_process(code: str, **env) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    result = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True,
                            check=True)
    return result.stdout.strip()


def test_import_sets_a_short_openmp_spin_unless_the_user_chose_or_torch_came_first():
    show = "import os; print(os.environ.get('GOMP_SPINCOUNT'))"
    assert _spin_count_in_fresh_process(f"import apmgsrn; {show}") == str(RUNTIME.spin_count)
    assert _spin_count_in_fresh_process(f"import apmgsrn; {show}", GOMP_SPINCOUNT="77") == "77"
    assert _spin_count_in_fresh_process(f"import apmgsrn; {show}", OMP_WAIT_POLICY="active") == "None"
    assert _spin_count_in_fresh_process(f"import torch, apmgsrn; {show}") == "None"


def test_inference_loops_on_the_cpu_try_thread_counts_and_restore_the_callers(monkeypatch):
    """query() (decode, eval) runs its batches under the process's inference governor."""
    from apmgsrn.inference.query import query
    from apmgsrn.threads import INFERENCE_THREADS, inference_governor

    seen = []

    class SlowField(torch.nn.Module):
        def forward(self, points):
            seen.append(torch.get_num_threads())
            time.sleep(0.004)
            return points[:, :1] * 2

    # As before its first probe: the governor is the process's, and a choice an earlier test's decode left it holding
    # (for up to max_hold_seconds) would otherwise run every batch on that one count.
    monkeypatch.setattr(INFERENCE_THREADS, "threads", None)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        points = torch.rand(100 * 64, 3)
        values = query(SlowField(), points, batch_size=64)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert torch.equal(values, points[:, 0] * 2)
    assert set(seen) == {1, 2} and INFERENCE_THREADS.history  # both timed, one chosen
    assert not inference_governor("cuda").enabled
