"""CPU kernels of the updates a training iteration makes after its gradients: Adam's step, and the pull of a
series step's features back towards where its fine-tune started.

Why: a series' step fine-tune trains only its feature tables (about 117,000 values for the hybrid's small
preset) at a small batch, one fused pass per iteration (:mod:`apmgsrn.ops.field_train_cpu`). PyTorch's Adam then
makes eight passes over them (lerp, mul, addcmul, sqrt, div, add, addcdiv, each a dispatched tensor operation
with its temporaries), and the pull six more: 0.43 ms of an iteration of about 8.4 ms on two threads
(``benchmarks/bench_step_updates.py``). Here Adam is two passes around PyTorch's own square root, and the pull
one.

Exactness: the arithmetic is ATen's, operation for operation, so training gives the same numbers as with
``torch.optim.Adam`` (its single-tensor CPU path) and the PyTorch pull, which the tests check bit for bit:

- ``exp_avg.lerp_(grad, w)`` with ``w < 0.5``: ATen's vectorised lerp is ``fma(w, grad - exp_avg, exp_avg)``;
- ``exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=c)``: ``fma(c * grad, grad, exp_avg_sq * beta2)``, the
  contraction ATen's build makes;
- the square root is PyTorch's own (``torch.sqrt``: on this CPU build MKL's, which is not always the correctly
  rounded one a C ``sqrtf`` gives);
- ``param.addcdiv_(exp_avg, sqrt / bc2_sqrt + eps, value=-step_size)``: ``param + (-step_size * exp_avg) / denom``;

every scalar rounded to float32 as ATen rounds it. Elsewhere the file has floating-point contraction off. Built
and cached like :mod:`apmgsrn.ops.trilinear_cpu`; callers fall back to their PyTorch reference where it cannot
be built.
"""

from __future__ import annotations

import torch

from apmgsrn.ops.kernel_cache import CompiledLibrary

C_SOURCE = r"""
#include <math.h>
#include <stdint.h>
typedef int64_t i64;

/* No contraction but the fused multiply-adds written out below, which are ATen's. */
#pragma GCC optimize ("fp-contract=off")

/* Below this many values a loop runs on one thread (ATen's grain size). */
#define GRAIN 32768

/* Adam's moments: exp_avg lerped towards grad by w (w < 0.5), exp_avg_sq times beta2 plus c * grad^2. */
void adam_moments(const float *grad, float *exp_avg, float *exp_avg_sq, i64 n, float w, float beta2, float c,
                  int nthreads) {
    #pragma omp parallel for schedule(static) num_threads(nthreads) if (n > GRAIN)
    for (i64 i = 0; i < n; ++i) {
        const float g = grad[i], m = exp_avg[i];
        exp_avg[i] = fmaf(w, g - m, m);
        exp_avg_sq[i] = fmaf(c * g, g, exp_avg_sq[i] * beta2);
    }
}

/* Adam's update of param from exp_avg and root = sqrt(exp_avg_sq). */
void adam_update(float *param, const float *exp_avg, const float *root, i64 n, float bc2_sqrt, float eps,
                 float neg_step, int nthreads) {
    #pragma omp parallel for schedule(static) num_threads(nthreads) if (n > GRAIN)
    for (i64 i = 0; i < n; ++i) {
        const float denom = root[i] / bc2_sqrt + eps;
        param[i] = param[i] + neg_step * exp_avg[i] / denom;
    }
}

/* param = start + sign(change) * max(|change| - threshold, 0), change = param - start. */
void pull_towards(float *param, const float *start, i64 n, float threshold, int nthreads) {
    #pragma omp parallel for schedule(static) num_threads(nthreads) if (n > GRAIN)
    for (i64 i = 0; i < n; ++i) {
        const float change = param[i] - start[i];
        const float sign = change > 0.0f ? 1.0f : (change < 0.0f ? -1.0f : 0.0f);
        const float shrunk = fabsf(change) - threshold;
        param[i] = start[i] + sign * (shrunk > 0.0f ? shrunk : 0.0f);
    }
}
"""


def _declare(lib) -> None:
    import ctypes

    p, i64, f32, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_int
    lib.adam_moments.argtypes = [p, p, p, i64, f32, f32, f32, i32]
    lib.adam_update.argtypes = [p, p, p, i64, f32, f32, f32, i32]
    lib.pull_towards.argtypes = [p, p, i64, f32, i32]
    for name in ("adam_moments", "adam_update", "pull_towards"):
        getattr(lib, name).restype = None


LIBRARY = CompiledLibrary("optimizer_cpu", C_SOURCE, _declare)


def fits(*tensors: torch.Tensor) -> bool:
    """Whether the kernels here can update these tensors in place: float32, contiguous, on the CPU, same size."""
    return all(t.device.type == "cpu" and t.dtype == torch.float32 and t.is_contiguous() and t.numel() ==
               tensors[0].numel() for t in tensors)


def adam_step_cpu(param: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor,
                  root: torch.Tensor, lerp_weight: float, beta2: float, square_weight: float,
                  bias_correction2_sqrt: float, eps: float, step_size: float) -> None:
    """One Adam step of ``param`` in place, as ``torch.optim.Adam`` makes it (module docstring): its moments
    ``exp_avg`` and ``exp_avg_sq`` (updated in place) from ``grad``, with ``lerp_weight = 1 - beta1`` (below 0.5),
    ``square_weight = 1 - beta2`` and the step's ``bias_correction2_sqrt`` and ``step_size`` (lr over the first
    bias correction); ``root`` is scratch space for the square root of ``exp_avg_sq``. All five tensors
    :func:`fits`."""
    lib = LIBRARY.load_or_raise()
    threads = torch.get_num_threads()
    n = param.numel()
    lib.adam_moments(grad.data_ptr(), exp_avg.data_ptr(), exp_avg_sq.data_ptr(), n, lerp_weight, beta2,
                     square_weight, threads)
    torch.sqrt(exp_avg_sq, out=root)
    lib.adam_update(param.data_ptr(), exp_avg.data_ptr(), root.data_ptr(), n, bias_correction2_sqrt, eps,
                    -step_size, threads)


def pull_towards_cpu(param: torch.Tensor, start: torch.Tensor, threshold: float) -> None:
    """Every value of ``param`` moved back towards ``start`` by ``threshold``, to ``start`` where it is closer (a
    soft threshold of the change), in place; both :func:`fits`."""
    lib = LIBRARY.load_or_raise()
    lib.pull_towards(param.data_ptr(), start.data_ptr(), param.numel(), threshold, torch.get_num_threads())
