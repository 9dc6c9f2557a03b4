"""Backend selection, in one place.

``cuda_ad_rgb`` is chosen when a CUDA device is present, ``llvm_ad_rgb``
otherwise. ``SLC_VARIANT`` (or the CLI's ``--variant``) overrides the choice.

Importing ``slc`` chooses no variant: the command line chooses it once (its ``--variant``), or
the first module that builds Mitsuba types on import does (the packages ``slc.scene``,
``slc.osc`` and ``slc.methods`` call :func:`ensure`); :func:`init` (``slc.set_variant``) before
that picks one.

Dr.Jit 1.5's LLVM backend needs libLLVM >= 16 (Debian's libLLVM 15 fails at
kernel compilation with "Cannot select ... fminimum"). Dr.Jit starts its LLVM
backend when it is imported, from ``DRJIT_LIBLLVM_PATH`` or its own search, so
``import slc`` (:func:`prepare`), before anything imports Dr.Jit, looks for a
suitable libLLVM, points ``DRJIT_LIBLLVM_PATH`` at it, and fails with a
one-line message otherwise; this module imports Dr.Jit only after that.
"""
from __future__ import annotations

import glob
import os
import platform
import re
import subprocess
import sys
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path

import numpy as np

SUPPORTED_VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")
MIN_LLVM = 16
# Ray settings of the local instances this package starts: worker processes at the driver's
# priority (Ray starts them at nice 15; beside three busy processes on 2 cores a worker's job
# then took 87 s, 60x its time at nice 0, since the scheduler gave it 1/30 of a core)
RAY_SYSTEM_CONFIG = {"worker_niceness": 0}
_LLVM_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib",
              "/usr/local/lib", "/usr/lib64", "/opt/homebrew/opt/llvm/lib",
              "/usr/local/opt/llvm/lib")
LLVM_HINT = ("install it with 'apt-get update && apt-get install -y libllvm19' "
             "(or run 'make run'), or set DRJIT_LIBLLVM_PATH to a libLLVM >= 16")


class BackendError(RuntimeError):
    """The rendering backend cannot be set up (one-line reason)."""


def _llvm_version(path: str) -> int | None:
    m = re.search(r"libLLVM[-.](?:so\.)?(\d+)", os.path.basename(path))
    if m:
        return int(m.group(1))
    m = re.search(r"libLLVM\.(\d+)", os.path.basename(path))  # macOS
    return int(m.group(1)) if m else None


def find_libllvm() -> str | None:
    """Path of the newest libLLVM >= 16 on this machine, or None."""
    best, best_v = None, -1
    for d in _LLVM_DIRS:
        for f in glob.glob(os.path.join(d, "libLLVM*")):
            v = _llvm_version(f)
            if v is not None and v >= MIN_LLVM and v > best_v:
                best, best_v = f, v
    return best


def _jit():
    """(drjit, mitsuba), imported after :func:`prepare`."""
    # Dr.Jit starts its LLVM backend on import: imported once DRJIT_LIBLLVM_PATH is set
    import drjit
    import mitsuba
    return drjit, mitsuba


def cuda_available() -> bool:
    dr, _ = _jit()
    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:
        return False


def prepare_llvm() -> None:
    """Point Dr.Jit at libLLVM >= 16 or raise a one-line BackendError."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        if not os.path.exists(env):
            raise BackendError(f"DRJIT_LIBLLVM_PATH={env} does not exist; {LLVM_HINT}")
        v = _llvm_version(env)
        if v is not None and v < MIN_LLVM:
            raise BackendError(f"DRJIT_LIBLLVM_PATH points at libLLVM {v}, Dr.Jit 1.5 needs >= {MIN_LLVM}; {LLVM_HINT}")
        return
    path = find_libllvm()
    if path is None:
        raise BackendError(f"no libLLVM >= {MIN_LLVM} found (Dr.Jit's CPU backend needs it); {LLVM_HINT}")
    os.environ["DRJIT_LIBLLVM_PATH"] = path


def prepare() -> None:
    """Point Dr.Jit at libLLVM >= 16 before it is imported (``import slc`` calls it; it chooses no
    variant), unless ``SLC_VARIANT`` asks for CUDA; a one-line BackendError otherwise."""
    if os.environ.get("SLC_VARIANT") != "cuda_ad_rgb":
        prepare_llvm()


def choose_variant(override: str | None = None) -> str:
    """The variant to use: override > $SLC_VARIANT > CUDA if present > LLVM."""
    v = override or os.environ.get("SLC_VARIANT")
    if v:
        if v not in SUPPORTED_VARIANTS:
            raise BackendError(f"unknown variant '{v}' (choose one of {', '.join(SUPPORTED_VARIANTS)})")
        return v
    return "cuda_ad_rgb" if cuda_available() else "llvm_ad_rgb"


_variant: str | None = None


def init(variant: str | None = None) -> str:
    """Select the Mitsuba variant once per process and return its name.

    The command line calls it with its ``--variant``, :func:`ensure` without; calling it again
    with a different explicit variant switches (only sensible before any module that builds
    Mitsuba types on import is imported)."""
    global _variant
    if _variant is not None and (variant is None or variant == _variant):
        return _variant
    want = variant or os.environ.get("SLC_VARIANT")
    if want != "cuda_ad_rgb":
        prepare_llvm()
    _, mi = _jit()
    v = choose_variant(variant)
    if v == "cuda_ad_rgb" and not cuda_available():
        raise BackendError("variant cuda_ad_rgb requested but no CUDA device is available")
    if v == "llvm_ad_rgb":
        prepare_llvm()
    mi.set_variant(v)
    _variant = v
    return v


def ensure() -> str:
    """The variant, chosen by :func:`init` unless chosen already: called on import by the packages
    whose modules build Mitsuba types on import. A :class:`BackendError` stops the import with its
    one line, not a traceback."""
    try:
        return init()
    except BackendError:
        sys.tracebacklimit = 0  # print the one-line reason, not a traceback
        raise


def variant() -> str:
    return init()


@contextmanager
def exr_pool():
    """Dr.Jit's thread pool with at least two threads while the block runs, its thread count
    before the block after it.

    Mitsuba's OpenEXR reader and writer wait for tasks that never run when the pool has fewer
    than two threads (``dr.set_thread_count(1)``, which a job runner or render node of one thread
    sets; there, loading a scene with an EXR environment map would never return). Scene loads,
    which read EXR textures and environment maps, and the EXR files of :mod:`slc.core.io` run
    inside it."""
    dr, _ = _jit()
    n = int(dr.thread_count())
    if n >= 2:
        yield
        return
    dr.set_thread_count(2)
    try:
        yield
    finally:
        dr.set_thread_count(n)


def env_info() -> dict:
    """Versions, CPU and variant: the ``env`` block of results.json."""
    dr, mi = _jit()
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "variant": variant(),
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH"),
    }


def code_version() -> str:
    """``git describe --always --dirty`` of the checkout the package runs from, else the
    installed package's version (``slc 0.1.0``)."""
    global _CODE_VERSION
    if _CODE_VERSION is None:
        try:
            r = subprocess.run(["git", "describe", "--always", "--dirty", "--tags"], capture_output=True, text=True,
                               cwd=Path(__file__).resolve().parents[1], timeout=10)
            _CODE_VERSION = r.stdout.strip() if r.returncode == 0 and r.stdout.strip() else None
        except (OSError, subprocess.SubprocessError):
            _CODE_VERSION = None
        if _CODE_VERSION is None:
            try:
                _CODE_VERSION = f"slc {metadata.version('slc')}"
            except metadata.PackageNotFoundError:
                _CODE_VERSION = "unknown"
    return _CODE_VERSION


_CODE_VERSION: str | None = None


def aligned(a, dtype):
    """A contiguous copy of ``a`` in a 64-byte aligned numpy buffer.

    Dr.Jit maps a numpy array without copying and marks it unaligned when its
    address is not a multiple of the vector width; every kernel reading it then
    differs (``align 1`` loads) from the one for an aligned array, so a kernel
    fed per-frame numpy data would be built again in whichever frame numpy's
    allocator returned the other kind of address."""
    a = np.ascontiguousarray(a, dtype)
    buf = np.empty(a.nbytes + 64, np.uint8)
    off = (-buf.ctypes.data) % 64
    out = buf[off:off + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out
