# `make demo` and `make test` each do all set-up on a fresh machine.
# The pinned CPU torch goes in first: an unpinned torch (direct or via a dependency) pulls a CUDA build.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= runs/demo

.PHONY: install install-ray demo test test-slow test-ray check-results check-wheel bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

# Optional: Ray, for --backend ray (docs/scaling.md); demo and test never need it.
install-ray: $(STAMP)
	$(PY) -m pip install -q -e ".[ray]"

demo: $(STAMP)
	$(VENV)/bin/bimp demo --out $(DEMO_OUT)

# Lint and import order first (ruff, configured in pyproject.toml): seconds, before minutes of tests. The tests run
# on every core (pytest-xdist), a test file per worker so that a file's compiled planners are built once.
test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q -n auto --dist loadfile

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

test-ray: install-ray
	$(PY) -m pytest -q -m slow tests/agents/test_backends.py

# Every results command of the README and docs/ with --dry-run against its committed folder: none may run an episode.
check-results: $(STAMP)
	$(PY) -m pytest -q tests/test_results_commands.py

# The built wheel in a fresh virtualenv beside PyPI's `envs`: both importable, only `bimp` installed, the CLI runs.
WHEEL_DIR := build/check-wheel
check-wheel: $(STAMP)
	rm -rf $(WHEEL_DIR) build/lib build/bdist.*  # setuptools' staging: a deleted module must not ship
	$(PY) -m pip wheel -q --no-deps --no-build-isolation -w $(WHEEL_DIR) .
	rm -rf bimp.egg-info  # the build leaves it in the checkout, where it would pass for the installed metadata
	$(PYTHON) -m venv $(WHEEL_DIR)/venv
	$(WHEEL_DIR)/venv/bin/python -m pip install -q torch==2.13.0
	$(WHEEL_DIR)/venv/bin/python -m pip install -q $(WHEEL_DIR)/bimp-*.whl envs
	cd $(WHEEL_DIR) && venv/bin/python -I $(CURDIR)/tests/check_wheel.py  # -I: no checkout folder on sys.path

bench: $(STAMP)
	$(VENV)/bin/bimp bench

clean:
	rm -rf $(VENV) runs .pytest_cache
