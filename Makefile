# ssm-ms: every target creates .venv and installs what is missing first.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
STAMP   = $(VENV)/.installed
LOGDIR ?= runs

.PHONY: install demo test test-slow tensorboard bench clean-data

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

install: $(STAMP)

## The main job on a CPU-sized default: learn the simple pendulum from noisy 24x24 images.
demo: $(STAMP)
	$(PY) cli.py fit --config configs/cpu/pendulum.yaml

## Unit and integration tests (< 10 minutes on 2 CPU cores).
test: $(STAMP)
	$(PY) -m pytest -q

## Long tests excluded from `make test`.
test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

tensorboard: $(STAMP)
	$(VENV)/bin/tensorboard --logdir $(LOGDIR)

## Speed figures, written to benchmarks/results/.
bench: $(STAMP)
	$(PY) benchmarks/bench_train_step.py
	$(PY) benchmarks/bench_pendulum_data.py
	$(PY) benchmarks/bench_lorenz_data.py
	$(PY) benchmarks/bench_moving_mnist.py
	$(PY) benchmarks/bench_ukf.py
