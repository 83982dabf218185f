# Fresh-machine entry points: `make demo` and `make test`; `make check` is the quick loop.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Small matrices: a multi-threaded BLAS only contends for the cores (see kpi_calib_ros/__init__.py).
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
# Byte code and pytest's rewritten test modules are cached (__pycache__/), whatever the
# shell says: rewriting the tests' asserts takes a worker seconds at every start.
unexport PYTHONDONTWRITEBYTECODE
# The tests run on TEST_WORKERS processes (pytest-xdist), handed out two at a time so that
# the long ones, collected first (test/conftest.py), spread over the workers; every worker
# holds a ROS domain of its own (test/ros_helpers.py).
TEST_WORKERS ?= 2
PYTEST := $(PY) -m pytest -q -n $(TEST_WORKERS) --maxschedchunk 2 --durations=15

.PHONY: install demo lint doc pictures check test test-slow bench clean

install: $(STAMP)

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip==24.3.1
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/kpi-calib demo --out demo_out

lint: $(STAMP)
	$(VENV)/bin/ruff check kpi_calib_ros test bench examples doc
	$(VENV)/bin/mypy kpi_calib_ros

# The documentation (doc/, reference pages generated from the code) with warnings as errors.
doc: $(STAMP)
	$(VENV)/bin/sphinx-build -q -W --keep-going -b html doc build/doc

# The pictures of the documentation, drawn by the tool on the simulated cell and on the
# real data of ../shared/data (minutes; not part of `make test`, whose
# test/test_doc_pictures.py fails when the plotting code changed after they were made).
pictures: $(STAMP)
	$(PY) doc/pictures.py

# The quick loop while editing: lint, types, the tests not marked slow.
check: lint
	$(PYTEST) -m "not slow" test

# What every change passes: lint and types first (they fail in seconds; mypy ~40 s without
# its cache), then the documentation (seconds), then every test not marked slow (minutes);
# the 15 slowest are listed.
test: lint doc
	$(PYTEST) -m "not slow" test

# The long studies: the tests marked slow (Monte Carlo, many seeds, the real campaigns, the
# node as a process through kills and restarts; about 13 minutes). CI runs them after
# `make test` (.ci/run).
test-slow: $(STAMP)
	$(PYTEST) -m slow test

bench: $(STAMP)
	$(PY) bench/run_all.py

clean:
	rm -rf $(VENV) build install log demo_out *.egg-info .mypy_cache .ruff_cache \
		doc/reference/_generated doc/_generated
