# Fresh-machine entry points: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Small matrices: a multi-threaded BLAS only contends for the cores (see kpi_calib_ros/__init__.py).
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1

.PHONY: install demo test bench clean

install: $(STAMP)

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip==24.3.1
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/kpi-calib demo --out demo_out

# Lint and types first: they fail in seconds (mypy ~40 s without its cache), the tests take minutes.
test: $(STAMP)
	$(VENV)/bin/ruff check kpi_calib_ros test bench
	$(VENV)/bin/mypy kpi_calib_ros
	$(PY) -m pytest -q test

bench: $(STAMP)
	$(PY) bench/run_all.py

clean:
	rm -rf $(VENV) build install log demo_out *.egg-info .mypy_cache .ruff_cache
