"""slc: shared caches of incoming light for many viewers, on Mitsuba 3 / Dr.Jit.

Importing the package selects the Mitsuba variant (see :mod:`slc.backend`):
``cuda_ad_rgb`` where a CUDA device exists, else ``llvm_ad_rgb``;
``SLC_VARIANT`` overrides. A missing libLLVM >= 16 raises a one-line
:class:`slc.backend.BackendError`.
"""
from . import backend

__version__ = "0.1.0"

backend.init()
