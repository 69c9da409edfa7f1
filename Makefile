# pporpe: two commands on a fresh machine.
#   make reproduce   the main job (installs what it needs into .venv first)
#   make test        lint, type-check and the test suite (installs what it needs first)
# Every install goes through constraints.txt, which pins torch to the CPU build 2.13.0.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip install -c constraints.txt
OUT    ?= results

.PHONY: reproduce test lint install install-dev bench clean

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PIP) --quiet -e .
	touch $@

$(VENV)/.installed-dev: $(VENV)/.installed
	$(PIP) --quiet -e ".[dev]"
	touch $@

install: $(VENV)/.installed
install-dev: $(VENV)/.installed-dev

## The main job: the paper's analytic figures into $(OUT)/figures.
reproduce: $(VENV)/.installed
	$(VENV)/bin/pporpe figures --out $(OUT)/figures

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

## The test suite: lint, types, then pytest.
test: lint
	$(PY) -m pytest -q

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
