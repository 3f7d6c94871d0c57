"""apmgsrn: adaptively placed multi-grid scene representation networks for scientific volumes.

Importing this package imports nothing heavy (the command line starts fast): it never initialises CUDA,
compiles kernels or imports torch or optional extras until a name below is used.
"""

from apmgsrn.errors import ApmgsrnError
from apmgsrn.threads import set_openmp_wait_policy

# Before torch loads libgomp, which reads its wait policy once: see apmgsrn.threads.
set_openmp_wait_policy()

__version__ = "0.1.0"
__all__ = ["ApmgsrnError", "Model", "load", "__version__"]


def __getattr__(name: str):
    # torch is imported on first use of the API, not by `import apmgsrn` (the CLI's start-up path).
    if name in ("Model", "load"):
        from apmgsrn import api

        return getattr(api, name)
    raise AttributeError(f"module 'apmgsrn' has no attribute {name!r}")
