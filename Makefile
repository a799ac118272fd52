# The two commands of the README. Both create .venv when it is missing and
# install the project into it (with MuJoCo Playground, which the environment
# tests use); they need only python3 and pip.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
INSTALLED := $(VENV)/.installed

.PHONY: train test test-fast

$(INSTALLED): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --constraint constraints.txt -e '.[dev,playground]'
	touch $(INSTALLED)

# A budget that finishes in a few minutes on a 2-core laptop; drop --epochs for the paper's 1000.
train: $(INSTALLED)
	$(BIN)/python scripts/train.py --poles 3 --epochs 60

# Compiling dominates the tests and XLA compiles a program on one core: one worker per core (at most
# four), each test module on one worker so that its shared compiled functions are built once.
PARALLEL := --numprocesses=auto --maxprocesses=4 --dist=loadscope

test: $(INSTALLED)
	$(BIN)/python -m pytest -q $(PARALLEL)

# The modules marked fast (pytestmark): closed forms, invariants and every task's gradients at a tiny
# horizon, under 2 minutes.
test-fast: $(INSTALLED)
	$(BIN)/python -m pytest -q -m "fast and not slow" $(PARALLEL)
