# pporpe: two commands on a fresh machine.
#   make reproduce   the main job: the quick grid + report (installs into .venv first)
#   make test        lint, type-check and the test suite (installs what it needs first,
#                    with the optional extras it tests: Ray, Stable-Baselines3, video)
# Every install goes through constraints.txt, which pins torch to the CPU build 2.13.0.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip install -c constraints.txt
OUT    ?= results

.PHONY: reproduce reproduce-paper reproduce-paper-full test lint install install-dev bench bench-sb3 clean

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PIP) --quiet -e .
	touch $@

$(VENV)/.installed-dev: $(VENV)/.installed
	$(PIP) --quiet -e ".[dev,ray,sb3,video]"
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
## One chunk at a time: make reproduce-paper ARGS="--tasks halfcheetah" (README: times per task).
reproduce-paper: $(VENV)/.installed
	$(VENV)/bin/pporpe reproduce experiments/paper.toml --out $(OUT)/paper --report $(ARGS)

## The same grid at the author's full lengths (HalfCheetah and Ant 2000 episodes, about 9-10
## hours per task on 2 cores): resumable, into results/paper-full (not committed).
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

## The test suite: lint, types, then pytest.
test: lint
	$(PY) -m pytest -q

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
