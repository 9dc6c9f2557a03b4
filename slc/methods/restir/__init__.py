"""ReSTIR DI: per-viewer reservoirs with temporal and spatial reuse."""
