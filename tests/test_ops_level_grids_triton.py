"""The hybrid model's Triton kernels (ops/level_grids_triton.py) against the PyTorch reference, forward and
backward: on CPU under ``TRITON_INTERPRET=1`` (in a subprocess, since Triton reads the flag when imported),
compiled ahead of time for sm_90 without a GPU, and on CUDA where there is one."""

import importlib.util
import inspect
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from apmgsrn.ops.level_grids import level_grid_features

HAS_TRITON = importlib.util.find_spec("triton") is not None
REPO = Path(__file__).resolve().parents[1]

# Layouts the kernels must get right: dense and hashed levels, 1 to 4 features, a 2-vertex axis, and the
# small preset of the hybrid model on a flat lattice (15 domain levels, 8 adaptive grids, maps moved).
CASE_CODE = """
import torch
from dataclasses import replace
from apmgsrn.models.registry import preset_config
from apmgsrn.models.encoders.hybrid_grid import HybridGridEncoder
from apmgsrn.ops.level_grids import index_space_maps, level_grid_features_reference
from apmgsrn.ops.level_layout import LevelLayout

def cases(device="cpu"):
    g = torch.Generator().manual_seed(0)
    out = []
    for layout in (LevelLayout(((4, 5, 6), (9, 7, 8), (6, 6, 2)), (2, 2, 1), (False, True, False), (120, 64, 72)),
                   LevelLayout(((3, 3, 3), (17, 9, 5)), (1, 4), (False, True), (27, 128))):
        levels = layout.levels
        matrices = torch.eye(3) + torch.randn(levels, 3, 3, generator=g) * 0.2
        translations = torch.randn(levels, 3, generator=g) * 0.2
        maps = index_space_maps(matrices, translations, torch.tensor(layout.resolutions, dtype=torch.float32))
        out.append((layout, maps, torch.randn(layout.table_size, generator=g)))
    config = replace(preset_config("hybrid", "small").encoder, lattice=(12, 20, 40))
    encoder = HybridGridEncoder(config, generator=g)
    with torch.no_grad():
        encoder.matrices.mul_(1.5)
        encoder.translations.add_(0.2)
    table = torch.randn(encoder.layout.table_size, generator=g)
    out.append((encoder.layout, encoder.maps().detach(), table))
    points = torch.rand(700, 3, generator=g) * 3.0 - 1.5
    points[:4] = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [2.0, 0.0, 0.0], [float("nan"), 0.0, 0.0]])
    return [(points.to(device), maps.to(device), table.to(device), layout) for layout, maps, table in out]

def forward_backward(fn, points, maps, table, layout):
    upstream = torch.randn(points.shape[0], layout.out_features, generator=torch.Generator().manual_seed(1))
    leaf = table.clone().requires_grad_(True)
    out = fn(points, maps, leaf, layout)
    (out * upstream.to(out.device)).sum().backward()
    return out.detach(), leaf.grad
"""


@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed")
def test_triton_kernels_match_the_reference_in_the_interpreter():
    code = CASE_CODE + textwrap.dedent("""
        from apmgsrn.ops import level_grids_triton as lt
        worst = 0.0
        for points, maps, table, layout in cases():
            # A NaN point reaches no corner (no memory touched) and its features are NaN, as the reference's.
            assert bool(torch.isnan(lt.forward_features(points[3:4], maps, table, layout)).all())
            points = torch.cat([points[:3], points[4:]])
            out, grad = forward_backward(lt.level_grid_features_triton, points, maps, table, layout)
            ref_out, ref_grad = forward_backward(level_grid_features_reference, points, maps, table, layout)
            torch.testing.assert_close(out, ref_out, atol=2e-5, rtol=1e-5)
            torch.testing.assert_close(grad, ref_grad, atol=2e-5, rtol=1e-5)
            worst = max(worst, (out - ref_out).abs().max().item())
        print("ok", worst)
        """)
    env = dict(os.environ, TRITON_INTERPRET="1", PYTHONPATH=str(REPO / "src"))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0 and proc.stdout.startswith("ok"), proc.stdout + proc.stderr


@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed")
def test_triton_kernels_compile_for_hopper_without_a_gpu():
    # Ahead-of-time lowering to sm_90 machine code, so kernels that only the interpreter ran are known to compile.
    import triton

    from apmgsrn.ops import level_grids_triton as lt

    try:
        from triton.backends.compiler import GPUTarget
        from triton.compiler import ASTSource
    except ImportError:
        pytest.skip("this triton has no ahead-of-time compile API")
    constants = {"FP": 2, "BLOCK": 256, "P1": 2654435761, "P2": 805459861}
    for kernel in (lt._forward_kernel, lt._backward_kernel):
        signature = {}
        for name in inspect.signature(kernel.fn).parameters:
            if name in constants:
                signature[name] = "constexpr"
            elif name == "info_ptr":
                signature[name] = "*i64"
            elif name.endswith("_ptr"):
                signature[name] = "*fp32"
            else:
                signature[name] = "i32"
        compiled = triton.compile(ASTSource(kernel, signature, constexprs=constants),
                                  target=GPUTarget("cuda", 90, 32), options={"num_warps": 4})
        assert len(compiled.asm["cubin"]) > 1000


def test_asking_for_triton_without_cuda_tensors_is_refused():
    from apmgsrn.ops.level_layout import LevelLayout

    layout = LevelLayout(((2, 2, 2),), (1,), (False,), (8,))
    with pytest.raises(RuntimeError, match="triton"):
        level_grid_features(torch.zeros(4, 3), torch.zeros(1, 3, 4), torch.zeros(8), layout, backend="triton")


@pytest.mark.gpu
def test_triton_matches_the_reference_on_cuda_and_auto_picks_it():
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    namespace: dict = {}
    exec(CASE_CODE, namespace)
    for points, maps, table, layout in namespace["cases"]("cuda"):
        points = torch.cat([points[:3], points[4:]])  # without the NaN point (the interpreter test has it)
        fused = namespace["forward_backward"](lambda *a: level_grid_features(*a, backend="auto"),
                                              points, maps, table, layout)
        reference = namespace["forward_backward"](namespace["level_grid_features_reference"],
                                                  points, maps, table, layout)
        torch.testing.assert_close(fused[0], reference[0], atol=2e-5, rtol=1e-5)
        # atomics add in another order: float32 summation differences
        torch.testing.assert_close(fused[1], reference[1], atol=1e-4, rtol=1e-4)
