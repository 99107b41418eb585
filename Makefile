# prism3d — set-up, tests, demo, benchmarks. `make demo` and `make test` do everything
# on a fresh machine (system libraries, a virtualenv, the package in editable mode).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Debian packages: open3d needs libusb; headless pyrender needs OSMesa; numba's OpenMP
# layer needs libgomp; the report is checked in a real headless Chromium.
SYS_PKGS := libusb-1.0-0 libosmesa6 libgl1 libegl1 libgomp1 chromium
export PYOPENGL_PLATFORM ?= osmesa
export NUMBA_THREADING_LAYER ?= omp
export MPLBACKEND ?= Agg
# test processes (pytest-xdist; 0 = one process): modules are spread whole (--dist loadfile),
# so module fixtures run once; the heaviest modules are scheduled first (tests/conftest.py;
# --no-loadscope-reorder keeps that order: xdist would put modules with few tests last)
TEST_WORKERS ?= 2

.PHONY: setup system-deps precompile test test-all demo bench clean help

help:
	@echo "make demo      install everything, then run the demo on built-in data (demo_out/report.html)"
	@echo "make test      install everything, then run the test suite"
	@echo "make test-all  also the slow tests"
	@echo "make bench     benchmarks against OpenCV / Open3D (benchmarks/RESULTS.md)"
	@echo "make setup     only install (system libraries + .venv), numba kernels compiled ahead"
	@echo "make precompile  compile the numba kernels again (after editing a kernel)"

system-deps:
	@missing=""; for p in $(SYS_PKGS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if ! $(PYTHON) -c "import venv, ensurepip" >/dev/null 2>&1; then missing="$$missing python3-venv"; fi; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing system packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	  else \
	    echo "missing system packages:$$missing"; \
	    echo "run: sudo apt-get install -y$$missing"; exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml constraints.txt
	@$(MAKE) --no-print-directory system-deps
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[test]'
	@# first run without waiting: byte-code of our sources (an editable install has none;
	@# ignored by git), then every numba kernel compiled into numba's on-disk cache
	$(PY) -m compileall -q prism3d capture reconstruct atr datasets
	$(PY) -m prism3d._precompile
	@# survey-detect's default recogniser (car, van, truck, bus), trained once into .venv's cache
	$(PY) -m prism3d.datasets.jobs.pretrain
	@touch $(STAMP)

setup: $(STAMP)

precompile: setup
	$(PY) -m prism3d._precompile

test: setup
	@set +e; $(PY) -m pytest -q -m "not slow" -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=30 $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing (a test run must run tests)"; exit 1; fi; \
	exit $$rc

test-all: setup
	$(PY) -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder $(PYTEST_ARGS)

demo: setup
	$(VENV)/bin/prism3d demo demo_out
	@echo "open demo_out/report.html"

bench: setup
	$(PY) benchmarks/run_all.py

clean:
	rm -rf demo_out .pytest_cache build *.egg-info
