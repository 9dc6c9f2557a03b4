"""Running: the frame loop, experiments, jobs on Ray, the command line and benchmarks."""
