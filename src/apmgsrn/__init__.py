"""apmgsrn: adaptively placed multi-grid scene representation networks for scientific volumes.

Importing this package never initialises CUDA, compiles kernels or imports optional extras.
"""

from apmgsrn.errors import ApmgsrnError

__version__ = "0.1.0"
__all__ = ["ApmgsrnError", "load", "__version__"]


def load(path, device="cpu"):
    """Load a model file (single or brick model) as a torch module mapping ``[N, 3]`` points in
    ``[-1, 1]^3`` to ``[N, 1]`` values in data units. Never executes code from the file."""
    from apmgsrn.training.checkpoint import load_model

    return load_model(path, device=device)
