"""Infrastructure: the Mitsuba variant, random-stream keys, frozen kernels, stage timing, check mode, file I/O."""
