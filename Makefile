# Two commands on a fresh machine: `make demo` (the main job) and `make test`.
# Each creates/refreshes .venv, installs torch==2.13.0 first (a CPU wheel here; a bare
# `torch` requirement would pull a multi-GB CUDA build), then the project with its extras.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv demo test bench clean

$(STAMP): pyproject.toml Makefile
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	# lpips declares a torchvision dependency; only its weight files are wanted.
	$(BIN)/python -m pip install -q --no-deps lpips==0.1.4
	# syncnet-python: the official SyncNet scoring code, an outside reference for the LSE tests
	# (installed without its declared dependencies, which would bring a broken torchvision).
	$(BIN)/python -m pip install -q --no-deps syncnet-python==0.2.3
	$(BIN)/python -m pip install -q -e '.[eval,test,cluster]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/lmgs-eval demo

# The suite in TEST_WORKERS processes (pytest-xdist), each test file whole in one of them (its
# module fixtures, e.g. a trained toy model, are made once); most tests keep one core busy.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile

# The speed benchmarks (ratios measured in one run), then the whole benchmark behind the
# committed tables/: the plan benchmarks/paper.toml (resumable from ./results). Serial by default;
# on a Ray cluster: make bench BENCH_ARGS="--executor ray --address HOST:PORT" (docs/cluster.md).
BENCH_ARGS ?=
bench: $(STAMP)
	$(BIN)/lmgs-eval bench all
	$(BIN)/lmgs-eval demo --full --plan benchmarks/paper.toml $(BENCH_ARGS)

clean:
	rm -rf $(VENV) build *.egg-info
