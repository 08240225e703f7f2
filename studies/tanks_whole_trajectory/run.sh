#!/usr/bin/env bash
# Cascaded Tanks, SSM-FC d = 4, multiple shooting over the whole training part (one trajectory of 819 samples, 39
# pieces of 21 tied by the gap term) instead of 5 windows of 200 in pieces of 25. 12 minutes per seed (the budget of
# configs/benchmarks/parts/base.yaml), the same validation (val_run_in: all) choosing the epoch kept; the test into
# this folder. Usage: bash studies/tanks_whole_trajectory/run.sh [SEED ...]   (from the repository root)
set -euo pipefail
PY=${PY:-.venv/bin/python}
DATA=--data.init_args.dir_placement=../shared/data/nonlinear_benchmarks
OUT=studies/tanks_whole_trajectory
for seed in "${@:-0 1 2}"; do
  $PY cli.py fit --config configs/benchmarks/cascaded_tanks_fc.yaml --seed_everything "$seed" $DATA \
    --data.init_args.window 819 --data.init_args.batch_size 1 --model.init_args.n_nodes 39 \
    --trainer.logger.init_args.version "whole-seed$seed"
  for kept in best last; do
    $PY cli.py test --config configs/benchmarks/cascaded_tanks_fc_test.yaml $DATA \
      --model.init_args.ssm_checkpoint "runs/cascaded_tanks_fc/whole-seed$seed/checkpoints/$kept.ckpt" \
      --model.init_args.results_dir $OUT --model.init_args.figures_dir $OUT \
      --model.init_args.method_name "SSM-FC (d = 4), whole trajectory, $kept epoch"
  done
done
