# Commands for a fresh machine: `make run`, `make test` (the whole suite) and `make check` (its fast tier).
# All three install what is missing (libLLVM >= 16, a .venv with the package) and are idempotent.
# Python 3.11 unless PYTHON names another (3.11-3.13 install: make PYTHON=python3.12 ...).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test check mutants install llvm bench clean

$(STAMP): pyproject.toml
	bash tools/ensure_llvm.sh
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	$(BIN)/python -m ipykernel install --sys-prefix --name python3 >/dev/null
	touch $(STAMP)

llvm:
	bash tools/ensure_llvm.sh

install: llvm $(STAMP)

# The first run: one viewer on the atrium, the shared caches slc (Surface Light Cones) and
# adaptive (the method to pick: per entry the representation its light needs) against 16 and 48
# light samples per pixel. 240x135 rather than the quick preset's 160x90: the caches' per-frame
# host time (Python tracing, syncs) does not grow with the pixels and weighs less there.
# Figures of a first run on an empty kernel cache: docs/results/make-run.md.
run: install
	@echo "make run: atrium 240x135, 24 frames (10 warm-up); adaptive and slc (shared caches) vs rt16 / rt48"
	@echo "(16 / 48 light samples + shadow rays per pixel); time = median direct-light ms per frame"
	@echo "after warm-up; FLIP / PSNR / SSIM against 2048-sample ground truth on frames 15 and 23."
	$(BIN)/slc run single-viewer --quick --res 240x135 --methods rt16 rt48 slc adaptive --sweep --out out

# The whole suite (what CI runs), with the 15 slowest tests listed at the end. Three worker
# processes on two cores (pytest-xdist; a test file stays on one worker, so its module fixtures
# are built once): most of the suite's time is Dr.Jit compiling kernels, one thread per process,
# and a third worker fills what tracing and waiting leave idle (whole suite on an empty kernel
# cache: 10 min 20 s with three, 10 min 12 s with two, in two runs one after the other).
# TEST_WORKERS=0 runs everything in this process.
# PYTEST = pytest with bytecode written even where PYTHONDONTWRITEBYTECODE is set: the suite starts
# about 80 Python processes (workers, fresh interpreters, command-line runs), each importing slc
# (0.3-0.4 s of CPU less from bytecode) and its test modules (assertions rewritten once).
TEST_WORKERS ?= 3
PYTEST := env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest
test: install
	$(PYTEST) -q -n $(TEST_WORKERS) --dist loadfile --durations=15 tests

# The fast tier, before every commit: unit tests, closed forms and one small render per
# method; the tests marked `slow` (see pyproject.toml) are left to `make test`. Two workers: the
# fast tier is almost all kernel compilation, which a third worker repeats rather than shares
# (on an empty kernel cache, 261 s of CPU with two workers against 300 s with three).
CHECK_WORKERS ?= 2
check: install
	$(PYTEST) -q -n $(CHECK_WORKERS) --dist loadfile -m "not slow" --durations=10 tests

# Named faults injected into the methods one at a time, in a temporary copy of the repository
# (tools/mutants.py; the list and the tests that kill each are in docs/testing.md): every fault
# must make its tests fail. Prints "killed K of N".
mutants: install
	$(BIN)/python tools/mutants.py

bench: install
	$(BIN)/slc bench rays

clean:
	rm -rf $(VENV) out
