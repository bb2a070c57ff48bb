# A newcomer's entry points. Everything installs into .venv from the package registry.
#   make demo   set up, then run the main job on an embedded default
#   make test   set up, then run the test suite (what CI runs)
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# The task to train for: a bundled spec's name (default, tote) or a spec file.
SCENE  ?= default
# The shipped task `make demo` runs on (default, tote, shelf).
TASK   ?= default
RUN    := $(if $(filter default,$(SCENE)),,_$(basename $(notdir $(SCENE))))

.PHONY: setup demo test test-unit test-all train ship bench lint clean

setup: $(STAMP)

$(STAMP): requirements.txt requirements-runtime.txt setup.py setup.cfg package.xml
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found; install Python 3.11 or run 'make PYTHON=python3.12 ...'"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

# The whole story on a small simulated bag: generate, start outcome_node, replay over DDS,
# record, score against ground truth, write a contact sheet and a summary.
demo: $(STAMP)
	$(PY) -m training demo --out runs/demo$(if $(filter default,$(TASK)),,_$(TASK)) --task $(TASK)

# Fast suite (CI): unit tests, the real node over DDS, a small end-to-end pipeline run.
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

# The pure-function tier alone: seconds, for the edit-test loop.
test-unit: $(STAMP)
	$(PY) -m pytest -q -m "unit and not slow"

# Everything, including the heavy tests.
test-all: $(STAMP)
	$(PY) -m pytest -q

# Quick retraining profile: 10,000 episodes of the task, 4 epochs at the training defaults
# (docs/training.md), about 21 min of epochs on 2 cores in fp32 (1.05 s a step), half that
# with native bf16. The weight average gets a shorter memory (0.993 per step) to match the
# ~1,200-step schedule. `make train SCENE=tote` trains the tote task.
train: $(STAMP)
	$(PY) -m training run --scene $(SCENE) --out runs/quick$(RUN) --episodes 10000 --epochs 4 \
		--ema-decay 0.993

# The shipped model of the task: 20,000 episodes, up to 13 epochs (the recipe of default
# model 0.19.0, tote model 0.21.0 and shelf model 0.18.0: a 6-26 min dataset and 41-57 min of
# epochs on 2 cores; the schedule fits the budget: 10 epochs of tote 0.9.0 on a slower machine,
# 13 of tote 0.21.0, 8 of shelf 0.18.0, 12 of default 0.19.0, all in bf16),
# installed into the package as the model named after the task (model_path:=tote). A task's
# own training options, if any, follow. The shelf's network reads 320 x 240 and trains on
# 160 x 120 crops of it, with outlier islands drawn at their own size (docs/training.md).
SHIP_OPTIONS_default := --aug-holes 0.5 --aug-noise 2.0 --aug-islands 3e-4 --aug-range-limit 0.5
SHIP_OPTIONS_tote := --relief-window-px 15 --relief-smoothing-px 3 --aug-holes 0.5 --aug-roll 15 \
	--aug-islands 3e-4
SHIP_OPTIONS_shelf := --input-size 320 240 --train-crop 160 120 --aug-holes 0.5 --aug-roll 15 \
	--aug-noise 2.0 --aug-islands 3e-4 --aug-islands-discs
ship: $(STAMP)
	$(PY) -m training run --scene $(SCENE) --out runs/$(basename $(notdir $(SCENE))) \
		--episodes 20000 --ship $(SHIP_OPTIONS_$(basename $(notdir $(SCENE))))

bench: $(STAMP)
	$(PY) bench/inference.py
	$(PY) bench/networks.py
	$(PY) bench/train_step.py
	$(PY) bench/node.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf build install log .pytest_cache
