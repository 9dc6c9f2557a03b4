"""The on-surface SH cache: the registered method ``sh`` (:mod:`slc.methods.sh.method`). The SH
basis, YCoCg encodings, projection and shading are in :mod:`slc.lib.sh`; see docs/sh-crc.md."""
