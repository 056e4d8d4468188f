# `make demo` and `make test` each do all set-up on a fresh machine.
# The pinned CPU torch goes in first: an unpinned torch (direct or via a dependency) pulls a CUDA build.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= runs/demo

.PHONY: install install-ray demo test test-slow test-ray bench clean

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

test: $(STAMP)
	$(PY) -m pytest -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

test-ray: install-ray
	$(PY) -m pytest -q -m slow tests/agents/test_backends.py

bench: $(STAMP)
	$(VENV)/bin/bimp bench

clean:
	rm -rf $(VENV) runs .pytest_cache
