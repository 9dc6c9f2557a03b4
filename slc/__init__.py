"""slc: shared caches of incoming light for many viewers, on Mitsuba 3 / Dr.Jit.

Importing the package selects the Mitsuba variant (see :mod:`slc.core.backend`):
``cuda_ad_rgb`` where a CUDA device exists, else ``llvm_ad_rgb``;
``SLC_VARIANT`` overrides. A missing or too old libLLVM (< 16) stops the
import with a one-line :class:`slc.core.backend.BackendError` saying how to
install it.
"""
from slc.core import backend

__version__ = "0.1.0"

try:
    backend.init()
except backend.BackendError:
    import sys
    sys.tracebacklimit = 0  # print the one-line reason, not a traceback
    raise
