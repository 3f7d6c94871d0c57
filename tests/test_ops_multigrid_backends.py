"""Every multi-grid backend against the PyTorch reference, forward and backward, on random inputs.

The CPU kernel is compiled once per machine (about a second with gcc) and cached; the Triton kernels
are checked on CPU under ``TRITON_INTERPRET=1`` (in a subprocess, since the flag is read when Triton
decorates the kernels) and on CUDA by the ``gpu`` tests.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest
import torch

from apmgsrn.ops import multigrid
from apmgsrn.ops.kernel_cache import CompiledLibrary
from apmgsrn.ops.multigrid import (
    feature_density,
    feature_density_reference,
    multigrid_features,
    multigrid_features_reference,
)

REPO = Path(__file__).resolve().parents[1]
HAS_COMPILER = bool(os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc"))
HAS_TRITON = importlib.util.find_spec("triton") is not None

# (M, C, (D, H, W)): the presets' shapes (smaller), odd sizes, one grid (fewer grids than threads),
# channels > 1 and a 2-voxel axis.
SHAPES = [(16, 1, (16, 16, 16)), (4, 2, (5, 7, 9)), (1, 3, (4, 4, 4)), (3, 4, (2, 6, 3))]


def random_case(m, c, size, n=3000, seed=0, spread=0.25, dtype=torch.float32):
    """Random maps and grids; points in [-1.6, 1.6]^3 so many fall outside or on a grid's border."""
    g = torch.Generator().manual_seed(seed)
    matrices = (torch.eye(3) + torch.randn(m, 3, 3, generator=g) * spread).to(dtype)
    translations = (torch.randn(m, 3, generator=g) * spread).to(dtype)
    grids = torch.randn(m, c, *size, generator=g).to(dtype)
    points = (torch.rand(n, 3, generator=g) * 3.2 - 1.6).to(dtype)
    # exact corner and border hits, where floor and the bounds test meet
    special = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 0.0],
                           [2.0, 0.0, 0.0], [-3.0, 0.5, 0.5], [0.3, 1.0, -0.2], [0.0, -1.0, 0.0]], dtype=dtype)
    points[: len(special)] = special[:n]
    return points, matrices, translations, grids


def forward_backward(fn, points, matrices, translations, grids, seed=1, fused=None):
    """Features and the gradient of a random projection of them w.r.t. the grids.

    ``fused``: when true, check that the output came from a fused kernel, not the reference.
    """
    leaf = grids.detach().clone().requires_grad_(True)
    out = fn(points, matrices, translations, leaf)
    if fused is not None:
        assert ("MultigridFunction" in type(out.grad_fn).__name__) == fused, type(out.grad_fn).__name__
    weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=out.dtype).to(out.device)
    (out * weights).sum().backward()
    return out.detach(), leaf.grad


def cpu_backend(points, matrices, translations, grids):
    return multigrid_features(points, matrices, translations, grids, backend="cpu")


@pytest.fixture(scope="module")
def cpu_kernel():
    if not HAS_COMPILER:
        pytest.skip("no C compiler: the CPU backend falls back to the reference")
    from apmgsrn.ops import multigrid_cpu

    assert multigrid_cpu.is_available(), multigrid_cpu.load_error()
    return multigrid_cpu


@pytest.mark.parametrize("m,c,size", SHAPES)
@pytest.mark.parametrize("threads", [1, 2])
def test_cpu_matches_reference(cpu_kernel, m, c, size, threads):
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        case = random_case(m, c, size, seed=m * 10 + c)
        out, grad = forward_backward(cpu_backend, *case, fused=True)
    finally:
        torch.set_num_threads(before)
    ref_out, ref_grad = forward_backward(multigrid_features_reference, *case)
    assert out.shape == ref_out.shape
    torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(grad, ref_grad, atol=2e-5, rtol=1e-5)
    assert (ref_out == 0).any()  # some points miss some grid: the skip path is exercised


def test_cpu_reads_channel_last_and_strided_inputs(cpu_kernel):
    points, matrices, translations, grids = random_case(5, 3, (6, 5, 4), seed=3)
    channel_last = cpu_kernel.channel_last(grids)
    assert channel_last.stride(1) == 1
    wide = torch.zeros(points.shape[0], 5)
    wide[:, 1:4] = points
    strided_points = wide[:, 1:4]  # not contiguous
    out, grad = forward_backward(cpu_backend, strided_points, matrices, translations, channel_last, fused=True)
    ref_out, ref_grad = forward_backward(multigrid_features_reference, points, matrices, translations, grids)
    torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(grad, ref_grad, atol=2e-5, rtol=1e-5)


def test_cpu_channel_last_copy_for_many_samples(cpu_kernel):
    # Enough samples per grid element that the forward pass reads a channel-last copy.
    points, matrices, translations, grids = random_case(2, 2, (4, 4, 4), n=200, seed=4)
    assert cpu_kernel._sampling_layout(grids, points.shape[0] * 2 * 2).stride(1) == 1
    out, grad = forward_backward(cpu_backend, points, matrices, translations, grids, fused=True)
    ref_out, ref_grad = forward_backward(multigrid_features_reference, points, matrices, translations, grids)
    torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(grad, ref_grad, atol=2e-5, rtol=1e-5)
    assert grad.stride() == grids.stride()  # the gradient keeps the parameter's layout


def test_cpu_moved_grids_skip_points(cpu_kernel):
    # Small grids far apart (grids that moved to features): most (point, grid) pairs are skipped.
    m = 6
    matrices = torch.eye(3).repeat(m, 1, 1) * 4
    centres = torch.linspace(-0.8, 0.8, m)[:, None] * torch.tensor([1.0, -1.0, 0.5])
    translations = -4 * centres
    grids = torch.randn(m, 2, 8, 8, 8)
    points = torch.rand(4000, 3) * 2 - 1
    out, grad = forward_backward(cpu_backend, points, matrices, translations, grids, fused=True)
    ref_out, ref_grad = forward_backward(multigrid_features_reference, points, matrices, translations, grids)
    assert (ref_out == 0).float().mean() > 0.8
    torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(grad, ref_grad, atol=2e-5, rtol=1e-5)


def test_empty_batch(cpu_kernel):
    points, matrices, translations, grids = random_case(3, 2, (4, 4, 4), n=0)
    out, grad = forward_backward(cpu_backend, points, matrices, translations, grids)
    assert out.shape == (0, 6) and torch.count_nonzero(grad) == 0


def test_point_gradients_fall_back_to_reference(cpu_kernel):
    # d features / d points is not in the kernel: the dispatcher must keep autograd exact.
    points, matrices, translations, grids = random_case(4, 2, (5, 5, 5), n=500, seed=5)
    grads = []
    for backend in ("cpu", "torch"):
        a = matrices.clone().requires_grad_(True)
        t = translations.clone().requires_grad_(True)
        p = points.clone().requires_grad_(True)
        out = multigrid_features(p, a, t, grids, backend=backend)
        assert "MultigridFunction" not in type(out.grad_fn).__name__  # the reference ran
        out.square().sum().backward()
        grads.append((a.grad, t.grad, p.grad))
    for got, want in zip(grads[0], grads[1]):
        torch.testing.assert_close(got, want)
        assert got.abs().sum() > 0


@pytest.mark.parametrize("m,c,size", SHAPES)
@pytest.mark.parametrize("threads", [1, 2])
def test_cpu_placement_gradients_match_reference(cpu_kernel, m, c, size, threads):
    """The reconstruction error moving the placement (a time-series step that drifts): the fused kernel's
    gradients for the maps and the grids, forward and backward, against the reference's."""
    points, matrices, translations, grids = random_case(m, c, size, seed=m * 10 + c + 1)
    results = []
    for backend in ("cpu", "torch"):
        before = torch.get_num_threads()
        torch.set_num_threads(threads if backend == "cpu" else before)
        try:
            leaves = [x.clone().requires_grad_(True) for x in (matrices, translations, grids)]
            out = multigrid_features(points, *leaves, backend=backend)
            assert ("MultigridFunction" in type(out.grad_fn).__name__) == (backend == "cpu")
            weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(2))
            (out * weights).sum().backward()
        finally:
            torch.set_num_threads(before)
        results.append((out.detach(), *(leaf.grad for leaf in leaves)))
    for got, want in zip(*results):
        scale = want.abs().max().clamp(min=1.0)
        torch.testing.assert_close(got / scale, want / scale, atol=2e-5, rtol=1e-4)
    assert results[1][1].abs().sum() > 0 and results[1][2].abs().sum() > 0


def test_float64_falls_back_to_reference(cpu_kernel):
    case = random_case(2, 1, (4, 4, 4), n=300, dtype=torch.float64)
    out = multigrid_features(*case, backend="cpu")
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, multigrid_features_reference(*case))


def test_auto_picks_the_cpu_kernel(cpu_kernel):
    assert multigrid.resolve_backend("auto", "cpu") == "cpu"
    assert multigrid.resolve_backend("torch", "cpu") == "torch"
    case = random_case(3, 1, (6, 6, 6), n=400)
    out, _ = forward_backward(multigrid_features, *case, fused=True)
    torch.testing.assert_close(out, multigrid_features_reference(*case), atol=2e-5, rtol=1e-5)


def test_unknown_or_unusable_backend_names():
    case = random_case(1, 1, (3, 3, 3), n=10)
    with pytest.raises(ValueError, match="unknown multigrid backend"):
        multigrid_features(*case, backend="cuda-magic")
    with pytest.raises(RuntimeError, match="triton"):
        multigrid_features(*case, backend="triton")  # CPU tensors
    assert multigrid.backend_available("triton", "cpu") is False


@pytest.mark.parametrize("power", [10, 1, 3])
@pytest.mark.parametrize("threads", [1, 2])
def test_cpu_feature_density_matches_reference(cpu_kernel, power, threads):
    g = torch.Generator().manual_seed(power)
    m = 7
    matrices = torch.eye(3) + torch.randn(m, 3, 3, generator=g) * 0.3
    translations = torch.randn(m, 3, generator=g) * 0.3
    points = torch.rand(2000, 3, generator=g) * 2.4 - 1.2
    upstream = torch.rand(2000, generator=g)
    results = []
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for fn in (feature_density, feature_density_reference):
            a = matrices.clone().requires_grad_(True)
            t = translations.clone().requires_grad_(True)
            rho = fn(points, a, t, power)
            assert ("Density" in type(rho.grad_fn).__name__) == (fn is feature_density)
            (rho * upstream).sum().backward()
            results.append((rho.detach(), a.grad, t.grad))
    finally:
        torch.set_num_threads(before)
    (rho, ga, gt), (ref_rho, ref_ga, ref_gt) = results
    torch.testing.assert_close(rho, ref_rho, rtol=1e-5, atol=1e-6)
    scale = ref_ga.abs().max()
    torch.testing.assert_close(ga / scale, ref_ga / scale, rtol=0, atol=2e-5)
    torch.testing.assert_close(gt / scale, ref_gt / scale, rtol=0, atol=2e-5)


def test_cpu_kernels_give_the_same_numbers_on_one_and_two_threads(cpu_kernel):
    """What lets the trainer change its thread count mid-run: with at least as many grids as threads, the
    features, the grid gradient and the density gradients do not depend on the thread count, bit for bit."""
    points, matrices, translations, grids = random_case(16, 1, (16, 16, 16), n=40000, seed=3)
    upstream = torch.rand(40000, generator=torch.Generator().manual_seed(4))
    results = []
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            features, grid_grad = forward_backward(cpu_backend, points, matrices, translations, grids, fused=True)
            a = matrices.clone().requires_grad_(True)
            t = translations.clone().requires_grad_(True)
            (feature_density(points, a, t, 10) * upstream).sum().backward()
            results.append((features, grid_grad, a.grad, t.grad))
    finally:
        torch.set_num_threads(before)
    for one, two in zip(*results):
        assert torch.equal(one, two)


def test_cpu_feature_density_far_points_give_zero_not_nan(cpu_kernel):
    matrices, translations = torch.eye(3)[None] * 3, torch.zeros(1, 3)
    points = torch.tensor([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [1e20, 1e20, 0.0]])
    a = matrices.clone().requires_grad_(True)
    rho = feature_density(points, a, translations, backend="cpu")
    rho.sum().backward()
    assert rho[0].item() == pytest.approx(27.0) and rho[1].item() == 0 and rho[2].item() == 0
    assert torch.isfinite(a.grad).all()


def test_feature_density_point_gradients_fall_back(cpu_kernel):
    points = (torch.rand(100, 3) * 2 - 1).requires_grad_(True)
    matrices, translations = torch.eye(3).repeat(2, 1, 1), torch.zeros(2, 3)
    feature_density(points, matrices, translations).sum().backward()
    assert points.grad is not None and points.grad.abs().sum() > 0


def run_python(code: str, env: dict[str, str] | None = None, timeout: float = 120) -> str:
    full_env = dict(os.environ)
    full_env.update(env or {})
    full_env["PYTHONPATH"] = str(REPO / "src") + os.pathsep + full_env.get("PYTHONPATH", "")
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=full_env,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def test_import_builds_nothing():
    out = run_python(
        """
        import sys
        import apmgsrn
        import apmgsrn.ops.multigrid
        import apmgsrn.models.encoders.adaptive_multigrid
        import apmgsrn.models.encoders.hybrid_grid
        from apmgsrn.ops import field_cpu, level_grids_cpu, multigrid_cpu, trilinear_cpu
        # The CPU kernel modules are imported (plain Python), but nothing is compiled or loaded until first use.
        loaded = [name for name in ("triton", "apmgsrn.ops.multigrid_triton") if name in sys.modules]
        kernels = (multigrid_cpu, field_cpu, trilinear_cpu, level_grids_cpu)
        built = [module.__name__ for module in kernels if module.LIBRARY.tried]
        print("loaded:", loaded, "built:", built)
        """
    )
    assert "loaded: [] built: []" in out


@pytest.fixture
def fresh_kernel_state(monkeypatch, tmp_path):
    """The CPU kernel module as if never loaded, with an empty cache; restored afterwards."""
    from apmgsrn.ops import multigrid_cpu

    monkeypatch.setenv("APMGSRN_CACHE", str(tmp_path / "cache"))
    library = multigrid_cpu.LIBRARY
    monkeypatch.setattr(multigrid_cpu, "LIBRARY", CompiledLibrary(library.name, library.source, library.declare))
    return multigrid_cpu


def test_falls_back_without_a_compiler(fresh_kernel_state, monkeypatch, tmp_path):
    # A build that cannot happen: auto uses the reference, an explicit "cpu" says why it cannot run.
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    points = torch.rand(50, 3) * 2 - 1
    maps = torch.eye(3)[None], torch.zeros(1, 3)
    grids = torch.randn(1, 1, 4, 4, 4)
    assert multigrid.resolve_backend("auto", "cpu") == "torch"
    assert torch.equal(multigrid_features(points, *maps, grids), multigrid_features_reference(points, *maps, grids))
    with pytest.raises(RuntimeError, match="no-such-compiler"):
        multigrid_features(points, *maps, grids, backend="cpu")
    density = feature_density(points, *maps)  # the density op falls back too
    torch.testing.assert_close(density, feature_density_reference(points, *maps))


@pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler")
def test_kernel_is_built_once_into_the_cache(fresh_kernel_state, tmp_path):
    module = fresh_kernel_state
    assert module.load_library() is not None, module.load_error()
    kernels = list((tmp_path / "cache" / "kernels").glob("multigrid_cpu_*.so"))
    assert len(kernels) == 1
    stamp = kernels[0].stat().st_mtime_ns
    module.LIBRARY.reset()  # as a new process would: finds the cached file, does not rebuild
    assert module.load_library() is not None
    assert kernels[0].stat().st_mtime_ns == stamp
    assert list((tmp_path / "cache" / "kernels").iterdir()) == kernels  # no temporary files left


@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed")
def test_triton_kernels_match_reference_in_interpreter():
    out = run_python(
        """
        import torch
        from apmgsrn.ops import multigrid_triton as mt
        from apmgsrn.ops.multigrid import multigrid_features_reference as ref
        worst = 0.0
        for seed, (m, c, size) in enumerate([(3, 1, (4, 5, 6)), (2, 3, (5, 4, 3)), (5, 2, (2, 3, 3))]):
            g = torch.Generator().manual_seed(seed)
            points = torch.rand(150, 3, generator=g) * 3.2 - 1.6
            points[:3] = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [2.0, 0.0, 0.0]])
            matrices = torch.eye(3) + torch.randn(m, 3, 3, generator=g) * 0.25
            translations = torch.randn(m, 3, generator=g) * 0.25
            grids = torch.randn(m, c, *size, generator=g)
            upstream = torch.randn(150, m * c, generator=g)
            results = []
            for fn in (mt.multigrid_features_triton, ref):
                leaf = grids.clone().requires_grad_(True)
                out = fn(points, matrices, translations, leaf)
                (out * upstream).sum().backward()
                results.append((out.detach(), leaf.grad))
            (out, grad), (ref_out, ref_grad) = results
            torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
            torch.testing.assert_close(grad, ref_grad, atol=2e-5, rtol=1e-5)
            # half-precision grids and a channel-last view: same values as the reference on them
            half = grids.half()
            lastc = grids.permute(0, 2, 3, 4, 1).contiguous().permute(0, 4, 1, 2, 3)
            torch.testing.assert_close(mt.forward_features(points, matrices, translations, half),
                                       ref(points, matrices, translations, half.float()), atol=2e-5, rtol=1e-5)
            torch.testing.assert_close(mt.forward_features(points, matrices, translations, lastc),
                                       ref_out, atol=2e-5, rtol=1e-5)
            worst = max(worst, (out - ref_out).abs().max().item())
        print("ok", worst)
        """,
        env={"TRITON_INTERPRET": "1"},
    )
    assert out.startswith("ok")


@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed")
@pytest.mark.parametrize("grid_type", ["*fp32", "*fp16", "*bf16"])
def test_triton_kernels_compile_for_hopper_without_a_gpu(grid_type):
    # Ahead-of-time lowering to sm_90 machine code (Triton's bundled ptxas), so kernels that only the
    # interpreter ran are known to compile; the GPU tests below also run them.
    import inspect

    import triton
    from apmgsrn.ops import multigrid_triton as mt

    try:
        from triton.backends.compiler import GPUTarget
        from triton.compiler import ASTSource
    except ImportError:
        pytest.skip("this triton has no ahead-of-time compile API")
    constants = {"M": 16, "C": 2, "CP": 2, "BLOCK": 512}
    for kernel, data in ((mt._forward_kernel, "grids_ptr"), (mt._backward_kernel, "grad_ptr")):
        signature = {}
        for name in inspect.signature(kernel.fn).parameters:
            if name in constants:
                signature[name] = "constexpr"
            elif name.endswith("_ptr"):
                signature[name] = "*fp32"
            else:
                signature[name] = "i32"
        if data == "grids_ptr":
            signature[data] = grid_type
        compiled = triton.compile(
            ASTSource(kernel, signature, constexprs=constants), target=GPUTarget("cuda", 90, 32),
            options={"num_warps": 4},
        )
        assert len(compiled.asm["cubin"]) > 1000


# ---- CUDA (skipped without a GPU) ----


def _cuda_case(m, c, size, n=20000, seed=0):
    return [t.cuda() for t in random_case(m, c, size, n=n, seed=seed)]


@pytest.mark.gpu
@pytest.mark.parametrize("m,c,size", SHAPES + [(16, 2, (32, 32, 32))])
def test_triton_matches_reference_on_cuda(m, c, size):
    case = _cuda_case(m, c, size)
    out, grad = forward_backward(lambda *a: multigrid_features(*a, backend="triton"), *case, fused=True)
    ref_out, ref_grad = forward_backward(multigrid_features_reference, *case)
    torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
    # atomics add in a different order: allow for float32 summation differences
    torch.testing.assert_close(grad, ref_grad, atol=1e-4, rtol=1e-4)


@pytest.mark.gpu
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_triton_half_precision_grids_on_cuda(dtype):
    points, matrices, translations, grids = _cuda_case(8, 2, (16, 16, 16), seed=3)
    half = grids.to(dtype)
    out, grad = forward_backward(
        lambda *a: multigrid_features(*a, backend="triton"), points, matrices, translations, half, fused=True
    )
    ref_out, _ = forward_backward(multigrid_features_reference, points, matrices, translations, half.float())
    torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
    assert out.dtype == torch.float32 and grad.dtype == dtype


@pytest.mark.gpu
def test_auto_picks_triton_on_cuda():
    if not HAS_TRITON:
        pytest.skip("triton is not installed")
    assert multigrid.resolve_backend("auto", "cuda") == "triton"
    case = _cuda_case(4, 2, (8, 8, 8), n=1000)
    out, _ = forward_backward(multigrid_features, *case, fused=True)
    torch.testing.assert_close(out, multigrid_features_reference(*case), atol=2e-5, rtol=1e-5)


PLANTED_SOURCE = r"""
#include <stdio.h>
__attribute__((constructor)) static void planted(void) {
    FILE *f = fopen(MARKER, "w");
    if (f) { fputs("ran", f); fclose(f); }
}
void mg_forward(void) {}
void mg_backward(void) {}
void mg_density(void) {}
void mg_density_backward(void) {}
"""


def _plant(path: Path, marker: Path) -> None:
    """A shared library named like the kernel whose constructor writes ``marker`` when it is loaded."""
    path.parent.mkdir(parents=True, exist_ok=True)
    source = path.parent / "planted.c"
    source.write_text(PLANTED_SOURCE)
    subprocess.run(["gcc", "-shared", "-fPIC", f'-DMARKER="{marker}"', str(source), "-o", str(path)], check=True)
    source.unlink()


def _kernel_name(module) -> str:
    from apmgsrn.ops.kernel_cache import COMMON_FLAGS, FLAG_SETS, cpu_signature, kernel_key

    compiler = shutil.which("gcc") or shutil.which("cc")
    return f"multigrid_cpu_{kernel_key(module.C_SOURCE, repr((COMMON_FLAGS, FLAG_SETS)), compiler, cpu_signature())}.so"


@pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler")
def test_an_unusable_cache_never_loads_a_kernel_planted_at_a_predictable_path(fresh_kernel_state, monkeypatch,
                                                                               tmp_path):
    module = fresh_kernel_state
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    monkeypatch.setenv("APMGSRN_CACHE", str(blocker / "cache"))  # cannot be created, even by root
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    marker = tmp_path / "planted-ran"
    uid = os.getuid() if hasattr(os, "getuid") else 0
    # Where the old code looked when the cache was unusable: a name any local user could predict.
    _plant(tmp_path / f"apmgsrn-kernels-{uid}" / _kernel_name(module), marker)
    assert module.load_library() is not None, module.load_error()
    assert not marker.exists()
    points = torch.rand(100, 3) * 2 - 1
    maps = torch.eye(3)[None], torch.zeros(1, 3)
    grids = torch.randn(1, 2, 4, 4, 4)
    torch.testing.assert_close(multigrid_features(points, *maps, grids, backend="cpu"),
                               multigrid_features_reference(points, *maps, grids))


@pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler")
def test_a_cache_others_can_write_or_a_file_they_own_is_not_trusted(fresh_kernel_state, tmp_path):
    module = fresh_kernel_state
    cache = tmp_path / "cache" / "kernels"
    marker = tmp_path / "planted-ran"
    _plant(cache / _kernel_name(module), marker)
    os.chmod(cache, 0o777)  # a folder anyone may write: whatever lies in it may have been swapped
    assert module.load_library() is not None, module.load_error()
    assert not marker.exists()
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        os.chmod(cache, 0o700)
        os.chown(cache / _kernel_name(module), 65534, 65534)  # the file belongs to someone else
        module.LIBRARY.reset()
        assert module.load_library() is not None, module.load_error()
        assert not marker.exists()
