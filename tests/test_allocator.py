"""glibc's allocator keeps freed memory for the next training step (apmgsrn.allocator)."""

import json
import os
import platform
import subprocess
import sys

import pytest

from apmgsrn.allocator import ALLOCATOR_VARIABLES

pytestmark = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                                reason="glibc's mallopt only")

# Where glibc puts a 4 MB block (a [16384, 64] float32 hidden layer) in a fresh process, and whether freeing it
# hands the memory back to the kernel; SETUP chooses the allocator's settings first. A block below the program
# break lies in the heap; a mapped one lies far above it.
PLACEMENT = """
import ctypes, json
SETUP
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.sbrk.restype, libc.sbrk.argtypes = ctypes.c_void_p, [ctypes.c_ssize_t]
libc.free.argtypes = [ctypes.c_void_p]
block = libc.malloc(4 << 20)
ctypes.memset(block, 1, 4 << 20)
brk = libc.sbrk(0)
libc.free(block)
print(json.dumps({"heap": block < brk, "kept": libc.sbrk(0) == brk}))
"""


def _run(code: str, **env) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in ALLOCATOR_VARIABLES}
    result = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True,
                            check=True, timeout=120)
    return result.stdout.strip().splitlines()[-1]


def _placement(setup: str, **env) -> dict:
    return json.loads(_run(PLACEMENT.replace("SETUP", setup), **env))


def test_import_serves_step_sized_blocks_from_the_heap_and_keeps_them_when_freed():
    assert _placement("import apmgsrn") == {"heap": True, "kept": True}
    # glibc's own start (apmgsrn's import then leaves it): mapped afresh, page by page, until it adapts
    assert _placement("import apmgsrn", GLIBC_TUNABLES="")["heap"] is False
    assert _placement("")["heap"] is False


def test_the_user_settings_stand():
    show = "import apmgsrn.allocator as a; print(a.keep_freed_memory())"
    assert _run(show) == "True"
    for name, value in (("MALLOC_TRIM_THRESHOLD_", "131072"), ("MALLOC_MMAP_THRESHOLD_", "131072"),
                        ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=131072")):
        assert _run(show, **{name: value}) == "False"
