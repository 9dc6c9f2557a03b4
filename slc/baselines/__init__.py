"""Baselines the caches must beat: random light sampling (RT-N) and ReSTIR DI."""
