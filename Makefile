# ssm-ms: every target creates .venv and installs what is missing first.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
STAMP   = $(VENV)/.installed
LOGDIR ?= runs
EXP    ?= pendulum
SIZE   ?= paper
# share of the CPU configs' epochs for the penalty / augmented-Lagrangian benchmark (13 variants each:
# ~35 min for the pendulum at 0.3, ~65 min for Lorenz at 0.2 on 2 cores; 1 = the configs as shipped)
CONSTRAINTS_PENDULUM ?= 0.3
CONSTRAINTS_LORENZ   ?= 0.2

.PHONY: install demo test format test-slow tensorboard bench reproduce peers control-pretrained

# torch as pyproject.toml pins it, installed by pip (which takes the machine's local CPU wheel where there is one; uv
# does not look there), then the rest by uv, which keeps that torch: ~60 s on a fresh machine, where pip alone took
# ~105 s (CI pays it on every clean clone)
TORCH = $(shell sed -n 's/^ *"\(torch==[^"]*\)".*/\1/p' pyproject.toml)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip uv
	$(PY) -m pip install --quiet "$(TORCH)"
	$(VENV)/bin/uv pip install --quiet --python $(PY) -e ".[dev]"
	@touch $(STAMP)

install: $(STAMP)

## The main job on a CPU-sized default: learn the simple pendulum from noisy 24x24 images.
demo: $(STAMP)
	$(PY) cli.py fit --config configs/cpu/pendulum.yaml

## Lint and format checks (ruff, configured in pyproject.toml), then the unit and integration tests (< 10 minutes on
## 2 CPU cores): two pytest workers of one torch thread each, since most tests keep one core busy (imports, small
## steps, subprocesses) and the suite ran single-core before. Work stealing: a worker that runs out of tests takes
## pending ones from the other, so both end together (xdist's default, load, left one idle at the end, measured in
## docs/tests.md). The 15 slowest tests are listed at the end: where the time goes when the suite nears its limit.
test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -n 2 --dist worksteal --durations=15

## Format the code and fix what ruff can (make test checks both).
format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

## deepSI, the peer of benchmarks/bench_deepsi.py (optional, never needed by `make test`): installed beside the pinned
## torch without its own dependencies (an unpinned torch would pull several GB of CUDA wheels), then those it needs.
## It asks for nonlinear_benchmarks < 0.2 but uses only its Input_output_data, which 1.0.1 (the benchmarks extra,
## the official loader's current release) has with the same signature.
peers: $(STAMP)
	$(PY) -m pip install --quiet --no-deps "deepsi==0.4.*"
	$(PY) -m pip install --quiet cloudpickle requests progressbar2 scipy  # its loader: the benchmarks extra's 1.0.1

## Long tests excluded from `make test`.
test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

tensorboard: $(STAMP)
	$(VENV)/bin/tensorboard --logdir $(LOGDIR)

## Speed figures, written to benchmarks/results/ (ssm-ms beside the reference structure, same-run ratios).
bench: $(STAMP)
	$(PY) benchmarks/bench_train_step.py
	$(PY) benchmarks/bench_train_step.py --threads 1 --rounds 4 --out benchmarks/results/train_step_threads1.md
	$(PY) benchmarks/bench_train_step.py --models SSM-LL --no-bf16 --inputs --out benchmarks/results/train_step_inputs.md
	$(PY) benchmarks/profile_decoder.py
	$(PY) benchmarks/profile_epoch.py
	$(PY) benchmarks/profile_decoder.py --cflags "-O3 -mavx2 -mfma -funroll-loops" --out benchmarks/results/decoder_profile_avx2.md
	$(PY) benchmarks/bench_pendulum_data.py
	$(PY) benchmarks/bench_lorenz_data.py
	$(PY) benchmarks/bench_moving_mnist.py
	$(PY) benchmarks/bench_ukf.py
	$(PY) benchmarks/bench_narrow_linear.py
	$(PY) benchmarks/bench_ddp_nodes.py
	$(PY) benchmarks/bench_allocator.py
	$(PY) benchmarks/bench_two_jobs.py
	$(PY) benchmarks/bench_constraints.py --experiments pendulum --fraction $(CONSTRAINTS_PENDULUM) \
		--out benchmarks/results/constraints_pendulum.md
	$(PY) benchmarks/bench_constraints.py --experiments lorenz_T1000 --fraction $(CONSTRAINTS_LORENZ) \
		--out benchmarks/results/constraints_lorenz_T1000.md

## One experiment end to end: SSM fit (-> its UKF, fitted-states, control tests) -> encoder fit -> test,
## results in results/$(EXP).md.
## make reproduce EXP=pendulum [SIZE=cpu] [SEED=N] [RESUME=reproduce-...] [ARGS="options for every stage"];
## EXP among pendulum pendulum_fc quad quad_fc mnist lorenz_T10 ... oscillator, and the identification benchmarks
## silverbox wiener_hammerstein emps cascaded_tanks (configs/benchmarks/; offline: ARGS="--data.init_args.dir_placement
## ../shared/data/nonlinear_benchmarks"; FOLDS=K: a benchmark's fit cross-validated over time, docs/benchmarks.md)
reproduce: $(STAMP) $(if $(filter oscillator,$(EXP)),data/oscillator.npz)
	$(PY) -m experiments.reproduce $(EXP) --size $(SIZE) $(if $(SEED),--seed $(SEED)) $(if $(FOLDS),--folds $(FOLDS)) $(if $(RESUME),--resume $(RESUME)) $(if $(ARGS),-- $(ARGS))

## The closed-loop tables' rows from pretrained/: each model of CONTROL_MODELS (pendulum_<model>.ckpt: torque, the
## camera; sensors, camera and joint angle; torque_amortised, the camera, nodes read from frames, its UKF on a chart of
## its states) with its UKF, then with its encoder where it has one, for each setting of CONTROL_SETTINGS
## it has a config for (control: |u| <= 3 N m; control_2nm: 2 N m), and the true model (the bound), 100 episodes
## each, into runs/pretrained/pendulum_control{,_2nm}.md (a few minutes per row on 2 cores).
CONTROL_SETTINGS ?= control control_2nm
CONTROL_MODELS ?= torque sensors torque_amortised
CONTROL_OUT = --model.init_args.results_dir runs/pretrained --model.init_args.figures_dir runs/pretrained/figures
control-pretrained: $(STAMP)
	set -e; for setting in $(CONTROL_SETTINGS); do \
		for model in $(CONTROL_MODELS); do \
			test -f pretrained/pendulum_$$model.ckpt || \
				{ echo "error: CONTROL_MODELS: no pretrained/pendulum_$$model.ckpt (shipped: torque sensors torque_amortised)" >&2; exit 2; }; \
			config=configs/pendulum_$${model}_$$setting.yaml; test -f $$config || continue; \
			ssm="--model.init_args.ssm_checkpoint pretrained/pendulum_$$model.ckpt"; \
			$(PY) cli.py test --config $$config $$ssm $(CONTROL_OUT) $(ARGS); \
			test -f pretrained/pendulum_$${model}_encoder.ckpt || continue; \
			$(PY) cli.py test --config $$config $$ssm \
				--model.init_args.encoder_checkpoint pretrained/pendulum_$${model}_encoder.ckpt $(CONTROL_OUT) $(ARGS); \
		done; \
		$(PY) cli.py test --config configs/pendulum_true_$$setting.yaml $(CONTROL_OUT) $(ARGS); \
	done

data/oscillator.npz: examples/make_oscillator_data.py
	$(PY) examples/make_oscillator_data.py --out $@
