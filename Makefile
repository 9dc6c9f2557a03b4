# Two commands for a fresh machine: `make run` and `make test`.
# Both install what is missing (libLLVM >= 16, a .venv with the package) and are idempotent.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test install llvm bench clean

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

run: install
	$(BIN)/slc run single-viewer --quick --out out

test: install
	$(BIN)/python -m pytest -q tests

bench: install
	$(BIN)/slc bench rays

clean:
	rm -rf $(VENV) out
