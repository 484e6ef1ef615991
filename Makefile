# Set-up and the two main jobs. `make demo` and `make test` each set up what they need first.
# TORCH: the torch requirement installed before meshseq. The default is the CPU wheel;
# with a CUDA torch already in your environment, run `make TORCH= setup` (or `pip install -e .`
# in that environment) and pip keeps the torch you have.
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin
STAMP := $(VENV)/.meshseq-installed

.PHONY: setup demo test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip "setuptools>=77"
	if [ -n "$(TORCH)" ]; then $(BIN)/python -m pip install --quiet "$(TORCH)"; fi
	$(BIN)/python -m pip install --quiet -e '.[test,bodies]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/meshseq demo --force

test: $(STAMP)
	tools/install_test_deps.sh
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/acap_speed.py

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info
