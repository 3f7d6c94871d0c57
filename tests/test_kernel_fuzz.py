"""Every point kernel and backend, and every model kind, at random, extreme and non-finite points: the answer the
contract of :mod:`apmgsrn.ops` documents, the same in every backend, forward and backward.

Each check runs in a child process, so a kernel that crashes (SIGSEGV) fails its test with the signal named,
instead of killing the test runner. Triton's kernels run under ``TRITON_INTERPRET=1`` where Triton is installed.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
HAS_TRITON = importlib.util.find_spec("triton") is not None

# Shared by every child: the fuzz points and the assertions of the contract.
PRELUDE = r"""
import itertools, math
import torch

torch.manual_seed(0)
NAN, INF = float("nan"), float("inf")
# extremes: the domain's faces, just past them, signed zero, denormals, huge, the largest float, infinities
SPECIAL = [0.0, -0.0, 1.0, -1.0, 1.0000001, -1.0000001, 0.5, -3.0, 1e-45, -1e-40, 1e30, -1e30, 3.4e38, -3.4e38,
           INF, -INF, NAN]


def fuzz_points(random=400, combos=None, seed=0):
    # random points in and around the domain, then every triple of special values (or `combos` of them)
    g = torch.Generator().manual_seed(seed)
    inside = torch.rand(random, 3, generator=g) * 3.0 - 1.5
    triples = torch.tensor(list(itertools.product(SPECIAL, repeat=3)), dtype=torch.float32)
    if combos is not None:
        triples = triples[torch.randperm(len(triples), generator=g)[:combos]]
    # special values mixed into random points, one coordinate at a time
    mixed = torch.rand(3 * len(SPECIAL), 3, generator=g) * 2.0 - 1.0
    for i, v in enumerate(SPECIAL):
        for axis in range(3):
            mixed[3 * i + axis, axis] = v
    return torch.cat([inside, triples, mixed]).contiguous()


def nan_rows(points):
    return torch.isnan(points).any(-1)


def infinite_rows(points):
    return torch.isinf(points).any(-1) & ~nan_rows(points)


def far_rows(points):
    # not NaN, and some coordinate beyond 1e29: outside every grid of these tests
    return (points.abs() > 1e29).any(-1) & ~nan_rows(points)


def check_rows(name, points, out):
    # NaN exactly at the points with a NaN coordinate, finite everywhere else
    bad = nan_rows(points)
    rows = out if out.dim() == 1 else out.reshape(out.shape[0], -1)
    isnan = torch.isnan(rows) if rows.dim() == 1 else torch.isnan(rows).all(-1)
    assert bool(isnan[bad].all()), f"{name}: a NaN point does not give NaN"
    assert bool(torch.isfinite(rows[~bad]).all()), f"{name}: a non-NaN point gives a non-finite value"


def same(name, a, b, atol=1e-5, rtol=1e-5):
    assert torch.equal(torch.isnan(a), torch.isnan(b)), f"{name}: NaN in other places"
    torch.testing.assert_close(a.nan_to_num(0.0), b.nan_to_num(0.0), atol=atol, rtol=rtol, msg=name)


def nan_upstream(points, shape):
    # the gradient a NaN loss sends back: NaN at the NaN points' rows
    g = torch.randn(shape, generator=torch.Generator().manual_seed(3))
    g[nan_rows(points)] = NAN
    return g


def grad_of(fn, points, upstream, *leaves):
    # gradients of fn(points, *leaves) with `upstream` sent back, and the same without the NaN points
    leaves = [x.detach().clone().requires_grad_(True) for x in leaves]
    out = fn(points, *leaves)
    grads = torch.autograd.grad(out, leaves, upstream, allow_unused=True)
    return out.detach(), grads
"""


def run_child(code: str, timeout: int = 600, **env_extra: str) -> str:
    """Run ``PRELUDE + code`` in a fresh interpreter; fail (naming a fatal signal) unless it prints ``ok``."""
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"), OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "2"),
               **env_extra)
    proc = subprocess.run([sys.executable, "-c", PRELUDE + textwrap.dedent(code)], capture_output=True, text=True,
                          env=env, timeout=timeout, cwd=REPO)
    if proc.returncode < 0:
        pytest.fail(f"the child died of {signal.Signals(-proc.returncode).name}:\n{proc.stdout}\n{proc.stderr[-4000:]}")
    assert proc.returncode == 0 and "ok" in proc.stdout.split(), proc.stdout + proc.stderr[-4000:]
    return proc.stdout


def test_ground_truth_samplers_clamp_to_the_border_and_give_nan_at_nan_points():
    run_child("""
        from apmgsrn.ops import trilinear_cpu
        from apmgsrn.ops.trilinear import sample_volume, sample_volume_reference
        from apmgsrn.ops.sparse_trilinear import sample_sparse_volume

        points = fuzz_points()
        volume = torch.rand(5, 6, 7)
        reference = sample_volume_reference(volume, points)
        check_rows("sample_volume reference", points, reference)
        # a point however far (inf included) samples what its clamp to the box samples
        clamped = torch.where(torch.isnan(points), points, points.clamp(-1, 1))
        same("border", reference, sample_volume_reference(volume, clamped), atol=0, rtol=0)
        if trilinear_cpu.LIBRARY.available():
            for threads in (1, 2):
                torch.set_num_threads(threads)
                same("sample_volume kernel", trilinear_cpu.sample_volume_cpu(volume, points), reference, atol=0, rtol=0)
        same("sample_volume", sample_volume(volume, points), reference, atol=0, rtol=0)
        # backward through the reference: finite, NaN points add nothing
        leaf = volume.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(sample_volume_reference(leaf, points), leaf, nan_upstream(points, (len(points),)))
        keep = ~nan_rows(points)
        (clean,) = torch.autograd.grad(sample_volume_reference(leaf, points[keep]), leaf,
                                       nan_upstream(points, (len(points),))[keep])
        same("sample_volume gradient", grad, clean)

        # the sparse sampler: a few stored voxels, the same answer as the dense volume they make
        dense = torch.zeros(5, 6, 7)
        indices = torch.tensor([0, 17, 40, 41, 100, 209])
        values = torch.rand(len(indices))
        dense.view(-1)[indices] = values
        sparse = sample_sparse_volume(indices, values, (5, 6, 7), points)
        check_rows("sparse", points, sparse)
        same("sparse against dense", sparse, sample_volume_reference(dense, points), atol=1e-3, rtol=0)
        assert bool(torch.isnan(sample_sparse_volume(indices[:0], values[:0], (5, 6, 7), points)[nan_rows(points)]).all())

        # the error guide's merge walk: positions stay in [0, N] whatever the queries
        from apmgsrn.ops import sorted_search_cpu
        if sorted_search_cpu.LIBRARY.available():
            running = torch.cumsum(torch.rand(1000, dtype=torch.float64), 0)
            queries = torch.tensor([-INF, -1e300, 0.0, 5.0, 1e300, INF], dtype=torch.float64)
            assert torch.equal(sorted_search_cpu.ascending_search_cpu(running, queries), torch.searchsorted(running, queries))
            odd = torch.tensor([NAN, -INF, NAN, INF, NAN], dtype=torch.float64)
            found = sorted_search_cpu.ascending_search_cpu(running, odd)
            assert bool(((found >= 0) & (found <= 1000)).all())
        print("ok")
    """)


def test_multigrid_kernels_are_zero_padded_everywhere_and_nan_at_nan_points():
    run_child("""
        from apmgsrn.ops import multigrid, multigrid_cpu
        from apmgsrn.ops.multigrid import feature_density, feature_density_reference, multigrid_features_reference

        points = fuzz_points()
        g = torch.Generator().manual_seed(1)
        m, c = 5, 3
        matrices = torch.eye(3) * 1.3 + torch.randn(m, 3, 3, generator=g) * 0.3
        matrices[0] = torch.diag(torch.tensor([0.9, 1.1, 1.0]))  # axis-aligned: Inf * 0 in its map
        translations = torch.randn(m, 3, generator=g) * 0.3
        grids = torch.randn(m, c, 4, 5, 6, generator=g)
        reference = multigrid_features_reference(points, matrices, translations, grids)
        check_rows("multigrid reference", points, reference)
        assert bool((reference[far_rows(points)] == 0).all()), "a point far outside has non-zero features"
        upstream = nan_upstream(points, reference.shape)
        keep = ~nan_rows(points)
        fn = lambda p, a, t, x: multigrid.multigrid_features(p, a, t, x, backend=backend)
        backend = "torch"
        _, ref_grads = grad_of(fn, points, upstream, matrices, translations, grids)
        _, clean = grad_of(fn, points[keep], upstream[keep], matrices, translations, grids)
        for name, a, b in zip(("matrices", "translations", "grids"), ref_grads, clean):
            assert bool(torch.isfinite(a).all()), f"reference gradient of {name} not finite"
            same(f"reference gradient of {name} without the NaN points", a, b)
        ref_density = feature_density_reference(points, matrices, translations)
        check_rows("density reference", points, ref_density)
        assert bool((ref_density[far_rows(points)] == 0).all())
        density_fn = lambda p, a, t: feature_density(p, a, t, backend=backend)
        _, ref_dgrads = grad_of(density_fn, points, nan_upstream(points, (len(points),)), matrices, translations)
        for grad in ref_dgrads:
            assert bool(torch.isfinite(grad).all()), "reference density gradient not finite"

        if multigrid_cpu.is_available():
            backend = "cpu"
            for threads in (1, 2):
                torch.set_num_threads(threads)
                for layout in (grids, multigrid_cpu.channel_last(grids)):
                    out, grads = grad_of(fn, points, upstream, matrices, translations, layout)
                    same("multigrid cpu", out, reference)
                    for name, a, b in zip(("matrices", "translations", "grids"), grads, ref_grads):
                        same(f"cpu gradient of {name}", a, b, atol=1e-4, rtol=1e-4)
                density, dgrads = grad_of(density_fn, points, nan_upstream(points, (len(points),)), matrices, translations)
                same("density cpu", density, ref_density, atol=1e-5, rtol=1e-4)
                for a, b in zip(dgrads, ref_dgrads):
                    same("density cpu gradient", a, b, atol=1e-3, rtol=1e-3)

            # the fused decoder: NaN at NaN points, the reference decoder's values elsewhere
            from apmgsrn.ops import field_cpu
            weights = [torch.randn(16, m * c, generator=g) * 0.3, torch.randn(16, 16, generator=g) * 0.3,
                       torch.randn(1, 16, generator=g)]
            with torch.no_grad():
                decoded = multigrid.multigrid_decoded(points, matrices, translations, grids, weights)
                x = reference
                for w in weights[:-1]:
                    x = torch.relu(x @ w.t())
                expected = (x @ weights[-1].t()).view(-1)
            assert decoded is not None
            check_rows("fused multigrid decoder", points, decoded)
            same("fused multigrid decoder", decoded, expected, atol=1e-4, rtol=1e-4)
        print("ok")
    """)


def test_level_grid_kernels_are_zero_padded_everywhere_and_nan_at_nan_points():
    run_child("""
        from apmgsrn.ops import level_grids, level_grids_cpu
        from apmgsrn.ops.level_grids import (index_space_maps, level_grid_features, level_grid_features_reference,
                                             level_grid_mse_step_reference, level_grid_mse_step, level_grid_decoded)
        from apmgsrn.ops.level_layout import LevelLayout

        points = fuzz_points()
        keep = ~nan_rows(points)
        g = torch.Generator().manual_seed(2)
        # dense and hashed levels, one and two features, a 2-vertex axis
        layout = LevelLayout(((4, 5, 6), (9, 7, 8), (6, 6, 2), (17, 9, 5)), (2, 2, 1, 4),
                             (False, True, False, True), (120, 64, 72, 128))
        matrices = torch.eye(3) + torch.randn(layout.levels, 3, 3, generator=g) * 0.2
        matrices[0] = torch.eye(3)  # axis-aligned: Inf * 0 in its map
        translations = torch.randn(layout.levels, 3, generator=g) * 0.2
        maps = index_space_maps(matrices, translations, torch.tensor(layout.resolutions, dtype=torch.float32))
        table = torch.randn(layout.table_size, generator=g)
        reference = level_grid_features_reference(points, maps, table, layout)
        check_rows("level-grid reference", points, reference)
        assert bool((reference[far_rows(points)] == 0).all()), "a point far outside has non-zero features"
        upstream = nan_upstream(points, reference.shape)
        fn = lambda p, t: level_grid_features(p, maps, t, layout, backend=backend)
        backend = "torch"
        _, (ref_grad,) = grad_of(fn, points, upstream, table)
        _, (clean,) = grad_of(fn, points[keep], upstream[keep], table)
        same("reference table gradient without the NaN points", ref_grad, clean)
        # gradients for the maps through the reference: finite
        leaf = maps.clone().requires_grad_(True)
        (map_grad,) = torch.autograd.grad(level_grid_features_reference(points, leaf, table, layout), leaf, upstream)
        assert bool(torch.isfinite(map_grad).all()), "reference map gradient not finite"

        weights = [torch.randn(16, layout.out_features, generator=g) * 0.3, torch.randn(16, 16, generator=g) * 0.3,
                   torch.randn(1, 16, generator=g)]
        target = torch.randn(len(points), generator=g)
        ref_pred, ref_step = level_grid_mse_step_reference(points, maps, table, layout, weights, target)
        check_rows("mse step reference", points, ref_pred)
        clean_pred, clean_step = level_grid_mse_step_reference(points[keep], maps, table, layout, weights, target[keep])
        # the mean runs over every point: NaN points count in N, add nothing to the sum
        same("mse step gradient without the NaN points", ref_step, clean_step * keep.sum() / len(points))

        if level_grids_cpu.is_available():
            backend = "cpu"
            for threads in (1, 2):
                torch.set_num_threads(threads)
                out, (grad,) = grad_of(fn, points, upstream, table)
                same("level-grid cpu", out, reference)
                same("level-grid cpu table gradient", grad, ref_grad, atol=1e-4, rtol=1e-4)
                with torch.no_grad():
                    decoded = level_grid_decoded(points, maps, table, layout, weights)
                assert decoded is not None
                same("fused level decoder", decoded, ref_pred, atol=1e-4, rtol=1e-4)
                step = level_grid_mse_step(points, maps, table, layout, weights, target)
                assert step is not None
                same("fused mse step prediction", step[0], ref_pred, atol=1e-4, rtol=1e-4)
                same("fused mse step gradient", step[1], ref_step, atol=1e-4, rtol=1e-4)
        print("ok")
    """)


@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed")
def test_triton_kernels_follow_the_contract_in_the_interpreter():
    run_child("""
        from apmgsrn.ops import level_grids_triton, multigrid_triton
        from apmgsrn.ops.level_grids import index_space_maps, level_grid_features_reference
        from apmgsrn.ops.level_layout import LevelLayout
        from apmgsrn.ops.multigrid import multigrid_features_reference

        points = fuzz_points(random=60, combos=400)
        keep = ~nan_rows(points)
        g = torch.Generator().manual_seed(4)
        m, c = 3, 2
        matrices = torch.eye(3) * 1.3 + torch.randn(m, 3, 3, generator=g) * 0.3
        matrices[0] = torch.eye(3)
        translations = torch.randn(m, 3, generator=g) * 0.3
        grids = torch.randn(m, c, 4, 5, 6, generator=g)
        reference = multigrid_features_reference(points, matrices, translations, grids)
        upstream = nan_upstream(points, reference.shape)
        out, (grad,) = grad_of(lambda p, x: multigrid_triton.multigrid_features_triton(p, matrices, translations, x),
                               points, upstream, grids)
        same("multigrid triton", out, reference)
        _, (ref_grad,) = grad_of(lambda p, x: multigrid_features_reference(p, matrices, translations, x),
                                 points, upstream, grids)
        same("multigrid triton gradient", grad, ref_grad, atol=1e-4, rtol=1e-4)

        layout = LevelLayout(((4, 5, 6), (9, 7, 8)), (2, 1), (False, True), (120, 64))
        lm = torch.eye(3) + torch.randn(layout.levels, 3, 3, generator=g) * 0.2
        lm[0] = torch.eye(3)
        maps = index_space_maps(lm, torch.randn(layout.levels, 3, generator=g) * 0.2,
                                torch.tensor(layout.resolutions, dtype=torch.float32))
        table = torch.randn(layout.table_size, generator=g)
        reference = level_grid_features_reference(points, maps, table, layout)
        upstream = nan_upstream(points, reference.shape)
        out, (grad,) = grad_of(lambda p, t: level_grids_triton.level_grid_features_triton(p, maps, t, layout),
                               points, upstream, table)
        same("level-grid triton", out, reference)
        _, (ref_grad,) = grad_of(lambda p, t: level_grid_features_reference(p, maps, t, layout), points, upstream, table)
        same("level-grid triton gradient", grad, ref_grad, atol=1e-4, rtol=1e-4)
        print("ok")
    """, TRITON_INTERPRET="1")


@pytest.mark.parametrize("kind", ["apmgsrn", "fvsrn", "ngp", "hybrid"])
def test_every_model_kind_predicts_nan_at_nan_points_and_finite_values_elsewhere(kind, tmp_path):
    run_child(f"""
        import apmgsrn
        from apmgsrn.io import SourceInfo, save_field
        from apmgsrn.models.field import NeuralField
        from apmgsrn.models.registry import preset_config

        kind = {kind!r}
        field = NeuralField(preset_config(kind, "small"), fit_min=-2.0, fit_max=3.0, volume_shape=(8, 9, 10),
                            generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            for p in field.encoder.parameters():
                if p.dim() > 2 or p.shape[0] > 64:  # grids and tables, not the grids' maps
                    p.normal_(generator=torch.Generator().manual_seed(1))
        path = {str(tmp_path / "m.apmgsrn")!r}
        save_field(path, field, SourceInfo(path="x.nc"), {{"iterations": 1}})
        model = apmgsrn.load(path)
        points = fuzz_points()
        values = torch.from_numpy(model.predict(points.numpy()))
        check_rows(kind + " predict", points, values)
        # the same numbers through every path a caller takes: the model, the batched query, tiny batches
        with torch.no_grad():
            direct = model(points).view(-1)
        same(kind + " predict against the model", values, direct, atol=1e-4, rtol=1e-4)
        small = torch.from_numpy(model.predict(points.numpy(), batch_size=7))
        same(kind + " predict in small batches", small, values, atol=1e-4, rtol=1e-4)
        # the reference (PyTorch) backends agree with the fused ones
        field = model.field
        for module in field.modules():
            config = getattr(module, "config", None)
            if config is not None and hasattr(config, "backend") and config.backend in ("auto", "cpu"):
                from dataclasses import replace
                module.config = replace(config, backend="torch")
        with torch.no_grad():
            reference = field(points).view(-1)
        same(kind + " fused against reference", values, reference, atol=1e-4, rtol=1e-4)
        # training-style backward through the reference: the encoder's gradients are finite (the decoder's weight
        # gradient multiplies a NaN point's NaN features by its zero gradient: NaN, as any matrix product's)
        field.zero_grad()
        out = field(points).view(-1)
        out[~nan_rows(points)].sum().backward()
        for name, p in field.encoder.named_parameters():
            assert p.grad is None or bool(torch.isfinite(p.grad).all()), f"{{kind}}: gradient of {{name}} not finite"
        print("ok")
    """)
