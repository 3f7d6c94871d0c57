"""apmgsrn: adaptively placed multi-grid scene representation networks for scientific volumes.

Importing this package imports nothing heavy (the command line starts fast): it never initialises CUDA,
compiles kernels or imports torch or optional extras until a name below is used.
"""

from apmgsrn.allocator import keep_freed_memory
from apmgsrn.errors import ApmgsrnError
from apmgsrn.threads import set_openmp_wait_policy

# Before torch loads libgomp, which reads its wait policy once: see apmgsrn.threads.
set_openmp_wait_policy()
# glibc's allocator keeps the memory a training step frees for the next one: see apmgsrn.allocator.
keep_freed_memory()

__version__ = "0.1.0"
__all__ = ["ApmgsrnError", "Model", "Region", "fit", "load", "plan", "render", "verify", "__version__"]

#: Names resolved on first use: torch comes with them, not with `import apmgsrn` (the CLI's start-up path).
_LAZY = {"Model": "apmgsrn.api", "fit": "apmgsrn.api", "load": "apmgsrn.api", "plan": "apmgsrn.api",
         "render": "apmgsrn.api", "verify": "apmgsrn.api", "Region": "apmgsrn.data.grid"}


def __getattr__(name: str):
    import importlib

    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'apmgsrn' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
