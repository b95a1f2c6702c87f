# `make demo` and `make test` each create .venv when missing or stale against
# pyproject.toml, install the project into it, then run. The demo installs only what it
# needs (the arm's client and the plots); the tests install the dev extra (everything).
# tools/install_venv.sh installs with uv (pip when uv cannot be had): 17 s here for the dev
# extra against pip's 43 s, the same versions. Neither compiles every installed module to
# bytecode (pip did, 15 s, before --no-compile); Python compiles what is imported, once,
# on first use.
# Python keeps the bytecode it compiles (__pycache__), whatever the shell says: with
# PYTHONDONTWRITEBYTECODE set, every stand-in, CLI call and pytest worker compiled numpy,
# scipy, FastAPI and rigctl from source again, 1.2 s of CPU per process start here
# (tests/test_cli.py: 22 s of CPU without the cache, 9 s with it).
unexport PYTHONDONTWRITEBYTECODE
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
DEMO_STAMP := $(VENV)/.installed-demo

.PHONY: demo test lint bench clean load-check wheel-check

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(VENV)/bin/python
	bash tools/install_venv.sh $(VENV) dev
	touch $(STAMP)

$(DEMO_STAMP): pyproject.toml | $(VENV)/bin/python
	bash tools/install_venv.sh $(VENV) arm,plots
	touch $(DEMO_STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

# Five pytest workers on two cores: much of an end-to-end test is waiting on simulated
# motion, which more workers fill (two -> three: 13.6 -> 11.6 min; three -> four: 8:55 ->
# 8:25; four -> five: 7:57 -> 6:47 of pytest on this machine, the slowest tests no slower:
# they wait more than they compute). --dist loadgroup hands out one test at a time to a
# free worker, the heavy ones first (tests/conftest.py); a module whose fixtures must be
# made once (the simulated rig of tests/test_e2e_default_world.py) is one xdist_group and
# goes to one worker. tools/load_check.py runs the suite with this many workers too.
# TEST_WORKERS=0 runs the suite in one process.
TEST_WORKERS ?= 5

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup --durations=25

# The suite on a busy machine: 3 runs of everything with two cores kept busy, then 10 runs
# of the end-to-end tests with one (tools/load_check.py; logs in load-check-logs/).
# Both parts always run (a failed suite run does not skip the end-to-end runs); the
# target fails when either part had a failed run.
load-check: $(STAMP)
	$(VENV)/bin/python tools/load_check.py --busy 2 --runs 3; suite=$$?; \
	$(VENV)/bin/python tools/load_check.py --busy 1 --runs 10 --e2e; e2e=$$?; \
	test $$suite -eq 0 && test $$e2e -eq 0

demo: $(DEMO_STAMP)
	$(VENV)/bin/python -m rigctl.demo

# The wheel, installed in a clean venv in an empty folder outside the source tree:
# `rigctl demo --quick` and a smoke test (.ci/wheel-check).
wheel-check:
	bash .ci/wheel-check

clean:
	rm -rf $(VENV) demo-records load-check-logs
