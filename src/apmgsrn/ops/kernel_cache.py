"""Build C kernels with the system compiler and cache them, trusting only files this user controls.

A shared library runs code when it is loaded, so a cached kernel is loaded only from a folder chain that
belongs to the current user and that nobody else can write (checked on every path component from the
cache root down, and on the file itself). When the cache cannot be used (read-only or full ``$HOME``, an
unwritable ``APMGSRN_CACHE``, a folder another user could write), the kernel is built into a fresh private
temporary folder (``mkdtemp``: mode 0700, unpredictable name) for this process alone: never into, or from,
a predictable shared path such as ``/tmp/apmgsrn-kernels-<uid>``.
"""

from __future__ import annotations

import atexit
import ctypes
import hashlib
import os
import platform
import shutil
import stat
import subprocess
import tempfile
import threading
from collections.abc import Callable, Sequence
from pathlib import Path


def cache_dir() -> Path:
    """Folder of built kernels: ``$APMGSRN_CACHE/kernels``, default ``~/.cache/apmgsrn/kernels``."""
    root = os.environ.get("APMGSRN_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "apmgsrn")
    return Path(root) / "kernels"


def cpu_signature() -> str:
    """What ``-march=native`` machine code depends on: the CPU's model and flags."""
    try:
        lines = [ln for ln in Path("/proc/cpuinfo").read_text().splitlines()
                 if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(lines)
    except OSError:
        return platform.processor() or platform.machine()


def kernel_key(*parts: str) -> str:
    """A short hash naming a kernel build (source, flags, compiler, CPU)."""
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()[:16]


def is_private(path: Path) -> bool:
    """True when ``path`` is owned by this user and writable by nobody else (no group/other write bit).

    Symbolic links are judged by what they point to only if the link itself is also ours.
    """
    if not hasattr(os, "getuid"):
        return True  # no POSIX ownership to check (not a platform this kernel builds on)
    try:
        info = path.lstat()
    except OSError:
        return False
    if info.st_uid != os.getuid() or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return False
    if stat.S_ISLNK(info.st_mode):
        return is_private(path.resolve())
    return True


def trusted_folder(folder: Path) -> bool:
    """Whether every component from ``folder`` up to the first one not created for the cache is private.

    The folder itself and its parents up to (not including) the user's home or the ``APMGSRN_CACHE`` root's
    parent must be private; a world-writable parent with the sticky bit (``/tmp``) is fine above that.
    """
    folder = folder.absolute()
    if not folder.is_dir() or not is_private(folder):
        return False
    for parent in folder.parents:
        try:
            info = parent.lstat()
        except OSError:
            return False
        writable_by_others = info.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
        if writable_by_others and not info.st_mode & stat.S_ISVTX:
            return False  # someone else could swap a folder on the way in
        if info.st_uid not in (0, os.getuid()):
            return False
    return True


def _make_private_folder(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)


def _compile(folder: Path, name: str, compiler: str, source: str, common_flags: Sequence[str],
             flag_sets: Sequence[Sequence[str]]) -> Path:
    """Compile ``source`` into ``folder / name``, trying the flag sets in order (atomic rename)."""
    errors = []
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        src = Path(tmp) / "kernel.c"
        src.write_text(source)
        out = Path(tmp) / name
        for extra in flag_sets:
            proc = subprocess.run([compiler, *common_flags, *extra, str(src), "-o", str(out), "-lm"],
                                  capture_output=True, text=True, timeout=300)
            if proc.returncode == 0:
                os.chmod(out, 0o700)
                target = folder / name
                os.replace(out, target)  # a concurrent process sees no file or a complete one
                return target
            errors.append(f"{' '.join(extra) or 'plain'}: {proc.stderr.strip()[-800:]}")
    raise RuntimeError(f"{compiler} could not build the kernel:\n" + "\n".join(errors))


def build_library(name: str, compiler: str, source: str, common_flags: Sequence[str],
                  flag_sets: Sequence[Sequence[str]]) -> Path:
    """The path of a loadable kernel library: the cached one if it is trusted, else a fresh build.

    Args:
        name: file name (include a :func:`kernel_key` so that another source or CPU gets another file).
        compiler: the C compiler.
        source: C source.
        common_flags: flags of every attempt.
        flag_sets: extra flags, tried in order until one compiles.

    Raises:
        RuntimeError: the compiler failed with every flag set.
    """
    folder = cache_dir()
    try:
        _make_private_folder(folder)
        if trusted_folder(folder):
            target = folder / name
            if target.exists() and is_private(target):
                return target
            return _compile(folder, name, compiler, source, common_flags, flag_sets)
    except OSError:
        pass  # read-only or full cache: build for this process below
    private = Path(tempfile.mkdtemp(prefix="apmgsrn-kernel-"))  # 0700, unpredictable
    atexit.register(shutil.rmtree, private, ignore_errors=True)  # loaded libraries stay mapped until exit
    return _compile(private, name, compiler, source, common_flags, flag_sets)


# Tried in order until one compiles: tuned for this CPU with OpenMP, then portable, then single-threaded.
# -fno-trapping-math lets gcc if-convert the float selects (else no loop vectorises); neither it nor
# -fno-math-errno changes a result, since the kernels never read errno or floating-point exception flags.
COMMON_FLAGS = ["-O3", "-fPIC", "-shared", "-fno-math-errno", "-fno-trapping-math", "-Wno-unknown-pragmas"]
FLAG_SETS = (
    ["-march=native", "-fopenmp"],
    ["-fopenmp"],
    [],
)


def find_compiler() -> str:
    """The C compiler: ``$CC`` when set, else gcc, else cc.

    Raises:
        RuntimeError: none is on ``PATH``.
    """
    wanted = os.environ.get("CC")
    compiler = shutil.which(wanted) if wanted else shutil.which("gcc") or shutil.which("cc")
    if compiler is None:
        raise RuntimeError(f"C compiler {wanted!r} not found" if wanted else "no C compiler (gcc or cc) on PATH")
    return compiler


class CompiledLibrary:
    """One C kernel library, built on first use (once per machine, cached as :func:`build_library` says)
    and loaded through :mod:`ctypes`, which releases the GIL during calls.

    Plain C without PyTorch headers compiles in a second or two. Linked with ``-fopenmp``, a kernel runs
    on PyTorch's own OpenMP pool: PyTorch ships ``libgomp.so.1`` under the same soname and loads it first,
    so ``torch.set_num_threads`` applies. When it cannot be built (no compiler), :meth:`load` returns
    ``None`` and :attr:`error` says why: callers fall back to their PyTorch reference.

    Args:
        name: file-name prefix of the build (the cached file is ``{name}_{key}.so``).
        source: the C source.
        declare: sets the ``argtypes``/``restype`` of the loaded library's functions.
    """

    def __init__(self, name: str, source: str, declare: Callable[[ctypes.CDLL], None]):
        self.name = name
        self.source = source
        self.declare = declare
        self._lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        """Forget the loaded library, as a new process would (the cached build stays)."""
        self._tried = False
        self._library: ctypes.CDLL | None = None
        self.error: str | None = None

    @property
    def tried(self) -> bool:
        """Whether this process has tried to build or load the library."""
        return self._tried

    def load(self) -> ctypes.CDLL | None:
        """The loaded library, built first if no trusted cached build exists; ``None`` if it cannot be."""
        with self._lock:
            if self._tried:
                return self._library
            self._tried = True
            try:
                compiler = find_compiler()
                key = kernel_key(self.source, repr((COMMON_FLAGS, FLAG_SETS)), compiler, cpu_signature())
                path = build_library(f"{self.name}_{key}.so", compiler, self.source, COMMON_FLAGS, FLAG_SETS)
                library = ctypes.CDLL(str(path))
                self.declare(library)
                self._library = library
            except Exception as err:  # noqa: BLE001 - any build problem means "use the reference"
                self.error = f"{type(err).__name__}: {err}"
                self._library = None
            return self._library

    def available(self) -> bool:
        """True when the library builds and loads on this machine."""
        return self.load() is not None

    def load_or_raise(self) -> ctypes.CDLL:
        """The loaded library.

        Raises:
            RuntimeError: it cannot be built here (with the reason).
        """
        library = self.load()
        if library is None:
            raise RuntimeError(f"the {self.name} kernel is not available: {self.error}")
        return library
