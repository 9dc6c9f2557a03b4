"""slc: shared caches of incoming light for many viewers, on Mitsuba 3 / Dr.Jit.

Importing the package chooses no Mitsuba variant (see :mod:`slc.core.backend`): the
command line chooses it (``--variant``), or the first module that builds Mitsuba types on
import does: ``cuda_ad_rgb`` where a CUDA device exists, else ``llvm_ad_rgb``;
``SLC_VARIANT`` overrides, and so does :func:`set_variant` called before. Importing it
points Dr.Jit at a libLLVM >= 16 (Dr.Jit starts its LLVM backend when imported); a missing
or too old libLLVM (< 16) stops the import with a one-line
:class:`slc.core.backend.BackendError` saying how to install it.
"""
import sys

from slc.core import backend
from slc.core.backend import init as set_variant  # noqa: F401

__version__ = "0.1.0"

try:
    backend.prepare()
except backend.BackendError:
    sys.tracebacklimit = 0  # print the one-line reason, not a traceback
    raise
