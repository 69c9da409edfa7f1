# pporpe: two commands on a fresh machine.
#   make reproduce   the main job: the quick grid + report (installs into .venv first)
#   make test        lint, type-check, the docs site and the test suite, at the same time,
#                    pytest on every core (installs what it needs first, with the optional
#                    extras it tests: Ray, SB3, video, docs, MuJoCo)
#   make docs        the documentation site into docs/_build/html (warnings are errors)
# Every install goes through constraints.txt, which pins torch to the CPU build 2.13.0.
# Installs skip pip's byte-compiling of every module it installs (a minute of one core for
# torch, Ray and the rest); Python writes a module's bytecode on its first import instead,
# so the recipes here keep it allowed even where PYTHONDONTWRITEBYTECODE is set.
unexport PYTHONDONTWRITEBYTECODE

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip install --no-compile -c constraints.txt
OUT    ?= results

.PHONY: reproduce reproduce-paper reproduce-paper-full test lint docs docs-pages suite install install-dev bench bench-sb3 clean

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet "pip>=23"
	$(PIP) --quiet -e .
	touch $@

# One pip run for the package and every extra the tests use (the docs' too), so a fresh
# clone's make test resolves and builds once.
$(VENV)/.installed-dev: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet "pip>=23"
	$(PIP) --quiet -e ".[dev,ray,sb3,video,docs,mujoco]"
	touch $(VENV)/.installed $(VENV)/.installed-docs $@

$(VENV)/.installed-docs: $(VENV)/.installed
	$(PIP) --quiet -e ".[docs,sb3]"
	touch $@

install: $(VENV)/.installed
install-dev: $(VENV)/.installed-dev

## The main job: the quick grid of the paper's comparison on the local process pool, then
## its report (summary table and figures), plus the analytic figures, all under $(OUT)/.
## Re-running resumes: finished runs are skipped, unfinished ones continue from checkpoints.
reproduce: $(VENV)/.installed
	$(VENV)/bin/pporpe figures --out $(OUT)/figures
	$(VENV)/bin/pporpe reproduce experiments/quick.toml --out $(OUT)/quick --report

## The paper's grid (3 methods x 4 tasks x 10 seeds) into results/paper, whose finished runs
## are committed: it resumes, training only what is missing, then rewrites REPORT.md.
## One chunk at a time: make reproduce-paper ARGS="--tasks halfcheetah" (results/paper/REPORT.md:
## times per task).
reproduce-paper: $(VENV)/.installed
	$(VENV)/bin/pporpe reproduce experiments/paper.toml --out $(OUT)/paper --report $(ARGS)

## The same grid at the author's full lengths (HalfCheetah and Ant 2000 episodes; CPU hours:
## the estimate in docs/results/throughput.md, the measured cost in the Compute line of
## results/paper-full/REPORT.md): resumable, into results/paper-full (its checkpoints
## ignored by git; experiments/collect.py commits runs trained in a folder elsewhere).
reproduce-paper-full: $(VENV)/.installed
	$(VENV)/bin/pporpe reproduce experiments/paper-full.toml --out $(OUT)/paper-full --report $(ARGS)

## Benchmarks (long): throughput, learning quality, and the batch trainer against SB3.
bench: bench-sb3
	$(PY) benchmarks/throughput.py
	$(PY) benchmarks/learning.py

## The batch trainer against Stable-Baselines3's PPO (installs SB3 for this only), ~20 min.
bench-sb3: $(VENV)/.installed
	$(PIP) --quiet -e ".[bench]"
	$(PY) benchmarks/vs_sb3.py $(ARGS)

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

## The documentation site (Sphinx, MyST Markdown) into docs/_build/html, warnings as errors,
## so a broken link or reference fails. First it checks that the generated pages (results
## pages, the README's results table) are what docs/generate.py writes from the committed
## results today, and that the README's headline figure was drawn from them;
## `make docs-pages` rewrites them (and redraws it) after new results.
docs: $(VENV)/.installed-docs
	$(PY) docs/generate.py --check
	$(VENV)/bin/sphinx-build -W --keep-going -q -b html docs docs/_build/html

docs-pages: $(VENV)/.installed
	$(PY) docs/generate.py
	$(PY) experiments/headline.py

## The test suite: lint and types, the docs site and pytest, the three at once, pytest on
## every core (pytest-xdist; the Ray tests on one worker, as they share a Ray head). Each
## one's output is printed whole when it ends (make's --output-sync), so a failure reads as
## it would alone; make test fails if any of them fails.
test: $(VENV)/.installed-dev
	$(MAKE) --no-print-directory -j3 --output-sync=target lint docs suite

## pytest alone, on every core.
suite: $(VENV)/.installed-dev
	$(PY) -m pytest -q -n auto --dist loadgroup

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache docs/_build docs/_autosummary
