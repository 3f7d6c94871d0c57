"""The CPU kernels of Adam's step and of the pull towards a fine-tune's start (ops/optimizer_cpu.py) against
PyTorch's Adam and the PyTorch pull: bit for bit, on a real series step's fine-tune and on values chosen to hit
every path (vector tails, zero changes, several parameter groups)."""

from __future__ import annotations

import os
import shutil

import pytest
import torch

from apmgsrn.data import open_volume
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.training.fit import prepare_values
from apmgsrn.training.optimizer import CpuAdam, pull_towards, pull_towards_reference
from apmgsrn.series.steps import PullTowardsStart
from apmgsrn.training.trainer import TrainConfig, Trainer

HAS_COMPILER = bool(os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc"))
pytestmark = pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler: the updates are PyTorch's")


@pytest.fixture(scope="module", autouse=True)
def kernel():
    from apmgsrn.ops import optimizer_cpu

    assert optimizer_cpu.LIBRARY.available(), optimizer_cpu.LIBRARY.error
    return optimizer_cpu


def gradients(shape, step: int) -> torch.Tensor:
    """Gradients over six orders of magnitude, some exactly zero (entries no point touched)."""
    generator = torch.Generator().manual_seed(step)
    scale = 10.0 ** torch.randint(-6, 1, shape, generator=generator).float()
    values = torch.randn(shape, generator=generator) * scale
    return values * (torch.rand(shape, generator=generator) > 0.2)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("betas", [(0.9, 0.99), (0.6, 0.999)])
def test_cpu_adam_steps_as_torch_adam_bit_for_bit(threads, betas):
    # sizes below and above the kernels' one-thread grain, none a multiple of a vector's width
    shapes = [(42_551,), (8, 21, 21, 21, 1), (7,)]
    start = [torch.randn(s, generator=torch.Generator().manual_seed(i)) * 0.1 for i, s in enumerate(shapes)]
    ours = [p.clone().requires_grad_(True) for p in start]
    theirs = [p.clone().requires_grad_(True) for p in start]

    def groups(params):  # two groups, one at a multiple of the rate, as the trainer's
        return [{"params": params[:2], "lr": 0.01}, {"params": params[2:], "lr": 0.003}]

    fast, reference = CpuAdam(groups(ours), betas=betas), torch.optim.Adam(groups(theirs), betas=betas)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for step in range(1, 25):
            for index, (a, b) in enumerate(zip(ours, theirs)):
                grad = gradients(a.shape, 100 * step + index)
                a.grad, b.grad = grad.clone(), grad.clone()
            if step == 5:  # a step in which one parameter has no gradient
                ours[1].grad = theirs[1].grad = None
            fast.step()
            reference.step()
            for a, b in zip(ours, theirs):
                assert torch.equal(a, b), f"step {step}: parameters differ by {(a - b).abs().max():.3g}"
    finally:
        torch.set_num_threads(before)
    for a, b in zip(ours, theirs):
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(fast.state[a][key], reference.state[b][key]), key
    # the same state, so a checkpoint written by one loads into the other
    assert fast.state_dict()["param_groups"] == reference.state_dict()["param_groups"]


def test_cpu_adam_falls_back_to_adam_where_the_kernel_does_not_apply():
    # float64 parameters and AMSGrad: the kernel takes neither, Adam's own step runs
    for params, options in [([torch.randn(100, dtype=torch.float64, requires_grad=True)], {}),
                            ([torch.randn(100, requires_grad=True)], {"amsgrad": True})]:
        twin = [p.detach().clone().requires_grad_(True) for p in params]
        fast, reference = CpuAdam(params, lr=0.01, **options), torch.optim.Adam(twin, lr=0.01, **options)
        for step in range(3):
            for a, b in zip(params, twin):
                a.grad = b.grad = gradients(a.shape, step).to(a.dtype)
            fast.step()
            reference.step()
        assert all(torch.equal(a, b) for a, b in zip(params, twin))
    # a closure, which makes the gradients itself: Adam's own step, the closure's loss returned
    ours, theirs = (torch.linspace(-1, 1, 100).requires_grad_(True) for _ in range(2))
    fast, reference = CpuAdam([ours], lr=0.01), torch.optim.Adam([theirs], lr=0.01)
    for optimizer, p in ((fast, ours), (reference, theirs)):
        def closure(p=p, optimizer=optimizer):
            optimizer.zero_grad()
            loss = (p**3).sum()
            loss.backward()
            return loss
        assert float(optimizer.step(closure).detach()) == float((torch.linspace(-1, 1, 100) ** 3).sum())
    assert torch.equal(ours, theirs)


def test_pull_kernel_is_the_pytorch_pull_bit_for_bit():
    start = torch.randn(70_001, generator=torch.Generator().manual_seed(1))
    change = gradients(start.shape, 2) * 1e-2
    change[:10] = torch.tensor([0.0, -0.0, 1e-4, -1e-4, 1e-4 + 1e-12, 3e-5, -3e-5, 1.0, -1.0, 2e-4])
    for threads in (1, 2):
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            fast, reference = start + change, start + change
            pull_towards(fast, start, 1e-4)
            pull_towards_reference(reference, start, 1e-4)
        finally:
            torch.set_num_threads(before)
        assert torch.equal(fast, reference)
        assert torch.equal(fast[:2], start[:2]) and bool((fast[2:4] == start[2:4]).all())  # within: back to start
        assert not torch.equal(fast, start)  # the large changes stay, shrunk


def test_a_real_step_fine_tune_with_the_kernels_is_the_pytorch_one_bit_for_bit(test_data, monkeypatch):
    """A series step's fine-tune (frozen decoder, tables and grids trained, pulled towards their start) on a real
    viscous-finger step: the trainer's CpuAdam and the kernel pull against torch.optim.Adam and the PyTorch pull."""
    path = test_data / "viscous_fingers_run01" / "031_density_031_064_2.0.vti"
    volume = open_volume(path)
    values = prepare_values(volume.to_numpy(), "none", 0.0, str(path), torch.device("cpu")).values
    config = TrainConfig(iterations=30, batch_size=4096, seed=0, density_start=31,
                         **training_defaults("hybrid"))

    def fine_tune(reference: bool) -> NeuralField:
        field = NeuralField(preset_config("hybrid", "small"), volume_shape=volume.shape,
                            generator=torch.Generator().manual_seed(0))
        field.requires_grad_(False)
        features = [field.encoder.level_table, field.encoder.grids]
        for p in features:
            p.requires_grad_(True)
        if reference:  # what ran before the kernels
            monkeypatch.setattr("apmgsrn.training.trainer.CpuAdam", torch.optim.Adam)
            monkeypatch.setattr("apmgsrn.series.steps.pull_towards", pull_towards_reference)
        Trainer(field, values, config, None, {}, [PullTowardsStart(features, 0.01)], warm=True).run()
        return field

    calls = {"adam": 0, "pull": 0}

    def counted(name, function):
        def call(*args):
            calls[name] += 1
            return function(*args)
        return call

    from apmgsrn.training import optimizer

    monkeypatch.setattr(optimizer, "adam_step_cpu", counted("adam", optimizer.adam_step_cpu))
    monkeypatch.setattr(optimizer, "pull_towards_cpu", counted("pull", optimizer.pull_towards_cpu))
    fast = fine_tune(False)
    assert calls == {"adam": 2 * 30, "pull": 2 * 30}  # the kernels made every update: two tensors, 30 iterations
    reference = fine_tune(True)
    for (name, a), (_, b) in zip(fast.state_dict().items(), reference.state_dict().items()):
        assert torch.equal(a, b), name
    trained = NeuralField(preset_config("hybrid", "small"), volume_shape=volume.shape,
                          generator=torch.Generator().manual_seed(0))
    assert not torch.equal(fast.encoder.level_table, trained.encoder.level_table)  # it did train
