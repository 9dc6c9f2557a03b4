"""Optional sub-stage clock of the ``osc-gi`` update (off by default: no host syncs then).

``Laps.lap(name, *values)`` evaluates ``values``, waits for the CPU work (``dr.sync_thread``) and
adds the time since the previous lap to ``name``. Enabled, it splits kernels that would otherwise
be fused: the split is indicative, the total a little higher than without it."""
from __future__ import annotations

import time

import drjit as dr


class Laps:
    def __init__(self, enabled: bool = False, skip: int = 0):
        self.enabled, self.ms, self.frames, self._t = bool(enabled), {}, 0, None
        self.skip, self._seen = int(skip), 0       # frames not counted (warm-up: kernel builds)

    def start(self) -> None:
        if self.enabled:
            self._seen += 1
            if self._seen == self.skip + 1:
                self.ms, self.frames = {}, 0
            dr.sync_thread()
            self._t = time.perf_counter()
            self.frames += 1

    def lap(self, name: str, *values) -> None:
        if not self.enabled or self._t is None:
            return
        if values:
            dr.eval(*values)
        dr.sync_thread()
        t = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (t - self._t) * 1e3
        self._t = t

    def per_frame(self) -> dict:
        return {k: v / max(self.frames, 1) for k, v in self.ms.items()}
