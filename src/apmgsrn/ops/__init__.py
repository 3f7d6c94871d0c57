"""Stateless maths. Pure-PyTorch references are always importable; accelerated backends load lazily.

Every point operation is defined on every input, and gives the same answer in every backend (the pure-PyTorch
reference, the C/OpenMP kernels, the Triton kernels):

- **Finite points outside** ``[-1, 1]^3``, however far: each operation's own formula. The ground-truth samplers
  (:func:`~apmgsrn.ops.trilinear.sample_volume`, :func:`~apmgsrn.ops.sparse_trilinear.sample_sparse_volume`)
  clamp to the border; the adaptive multi-grid and level-grid encodings are zero-padded (a grid or level whose
  lattice does not cover a point contributes 0, so beyond every grid the features are 0); the feature density
  falls to 0.
- **Infinite coordinates** (``±inf``) behave like a finite point far outside on that side: the border value,
  zero features, zero density. A map that turns them into a non-finite index coordinate (``inf * 0``,
  ``inf - inf``) counts as outside.
- **A NaN coordinate**: every output of that point is NaN (its samples, features, density, decoded value), and
  the point adds nothing to any gradient the kernels compute (table, grids, placement), whatever gradient
  comes back for it.

The guarantee holds inside the kernels, not only at an entry point: index coordinates are clamped or masked in
floating point, NaN-safe, before any integer conversion (a float-to-int cast of NaN, Inf or a huge value is
undefined behaviour in C), so no input reads or writes outside a table, forward or backward.
:mod:`apmgsrn.ops.contract` holds the references' helpers; ``tests/test_kernel_fuzz.py`` feeds random, extreme
and non-finite points through every kernel, backend and model kind and checks this.
"""
