"""The updates after a training iteration's gradients, on the CPU through :mod:`apmgsrn.ops.optimizer_cpu` where
it applies, else PyTorch's: Adam (:class:`CpuAdam`) and the pull of features back towards where a fine-tune
started (:func:`pull_towards`). Both give the same numbers either way (``tests/test_optimizer_cpu.py``)."""

from __future__ import annotations

import torch

from apmgsrn.ops.optimizer_cpu import LIBRARY, adam_step_cpu, fits, pull_towards_cpu


class CpuAdam(torch.optim.Adam):
    """``torch.optim.Adam`` whose steps run as the CPU kernel of :mod:`apmgsrn.ops.optimizer_cpu` where they can
    (float32 CPU tensors, dense gradients, the plain algorithm: no weight decay, AMSGrad, maximising or
    differentiable steps, ``1 - beta1`` below 0.5; the kernel built), else as Adam's own. Same state, same
    checkpoints, the same numbers bit for bit."""

    def __init__(self, params, *args, **kwargs):
        super().__init__(params, *args, **kwargs)
        self._roots: dict[torch.Tensor, torch.Tensor] = {}

    def _plain(self, group: dict) -> bool:
        return (not group["amsgrad"] and not group["maximize"] and not group["weight_decay"]
                and not group["differentiable"] and not group["capturable"] and not group["fused"]
                and not isinstance(group["lr"], torch.Tensor) and 1 - group["betas"][0] < 0.5)

    @torch.no_grad()
    def step(self, closure=None):
        """One step of every parameter with a gradient; with a ``closure`` (which makes the gradients, so they
        cannot be checked before), Adam's own step."""
        if closure is not None or not all(self._plain(group) for group in self.param_groups) \
                or not LIBRARY.available():
            return super().step(closure)
        pairs = [(p, p.grad) for group in self.param_groups for p in group["params"] if p.grad is not None]
        if not all(not grad.is_sparse and fits(p, grad) for p, grad in pairs):
            return super().step()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:  # as Adam starts a parameter's state
                    state["step"] = torch.tensor(0.0, dtype=_step_dtype())
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["step"] += 1
                step = state["step"].item()
                # Adam's scalars, in double precision as it forms them
                step_size = group["lr"] / (1 - beta1**step)
                bias_correction2_sqrt = (1 - beta2**step) ** 0.5
                root = self._roots.get(p)
                if root is None:  # scratch, not state: checkpoints stay Adam's
                    root = self._roots[p] = torch.empty_like(p)
                adam_step_cpu(p, p.grad, state["exp_avg"], state["exp_avg_sq"], root, 1 - beta1, beta2, 1 - beta2,
                              bias_correction2_sqrt, group["eps"], step_size)
        return None


def _step_dtype() -> torch.dtype:
    """The dtype Adam keeps a parameter's step count in (off the fused and capturable paths)."""
    return torch.float64 if torch.get_default_dtype() == torch.float64 else torch.float32


def pull_towards_reference(param: torch.Tensor, start: torch.Tensor, threshold: float) -> None:
    """:func:`pull_towards` in PyTorch operations (what the kernel is checked against)."""
    change = param - start
    param.copy_(start + change.sign() * (change.abs() - threshold).clamp_min(0))


@torch.no_grad()
def pull_towards(param: torch.Tensor, start: torch.Tensor, threshold: float) -> None:
    """Every value of ``param`` moved back towards ``start`` by ``threshold``, to ``start`` where it is closer (the
    proximal step of an L1 penalty on the change), in place."""
    if fits(param, start) and LIBRARY.available():
        pull_towards_cpu(param, start, threshold)
    else:
        pull_towards_reference(param, start, threshold)
