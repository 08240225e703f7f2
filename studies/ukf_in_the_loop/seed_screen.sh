#!/bin/bash
# Issue 80, item 2's untried candidate (README point 20): the shipped amortised config
# (configs/pendulum_torque_amortised.yaml, 420 epochs) with seed S, a checkpoint kept every 20 epochs, then its
# closed loop with the chart UKF (configs/pendulum_torque_amortised_control.yaml) on the 20 *tuning* starts (data and
# planner seed 10, not the table's) at epochs 300 and 420: the seed and epoch whose loop balances most is chosen there,
# and only that one is then scored on the table's 100 episodes. Resumable: run it again after a stop (the fit goes on
# from its last.ckpt). ~85-100 min a seed on 2 CPU cores (~14 s an epoch; ~25 s on the slowest CPU
# seen), ~2 min a loop. From the repository root:
#   bash studies/ukf_in_the_loop/seed_screen.sh SEED
# -> runs/seed_screen/seed<S>.log (the fit), runs/seed_screen/loop_seed<S>_e<E>/ (each loop's results), and one line
#    per loop in runs/seed_screen/scores.txt (successes over the 20, final error; copy them into the study's notes).
set -euo pipefail
cd "$(dirname "$0")/../.."
S=${1:?usage: seed_screen.sh SEED}
source .venv/bin/activate
OUT=runs/seed_screen
mkdir -p "$OUT"
V=seed_screen_s$S
D=runs/pendulum_torque_amortised/$V/checkpoints
RESUME=()
if [ -e "$D/last.ckpt" ]; then RESUME=(--ckpt_path "$D/last.ckpt"); fi
if [ ! -e "$D/keep-epoch=419.ckpt" ]; then
  python cli.py fit --config configs/pendulum_torque_amortised.yaml --seed_everything "$S" \
    --trainer.logger.init_args.version "$V" \
    "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint" --trainer.callbacks.every_n_epochs=20 \
    --trainer.callbacks.save_top_k=-1 "--trainer.callbacks.filename=keep-{epoch}" \
    --trainer.callbacks.save_on_train_epoch_end=true --trainer.enable_progress_bar=false "${RESUME[@]}" \
    >> "$OUT/seed$S.log" 2>&1
fi
for E in 299 419; do
  R=$OUT/loop_seed${S}_e$E
  [ -e "$R/pendulum_control.md" ] && continue
  python cli.py test --config configs/pendulum_torque_amortised_control.yaml \
    --model.init_args.ssm_checkpoint "$D/keep-epoch=$E.ckpt" --data.init_args.seed 10 --model.init_args.seed 10 \
    --data.init_args.n_test 20 --model.init_args.results_dir "$R" --model.init_args.figures_dir null \
    --trainer.logger false --trainer.default_root_dir "$R" --trainer.enable_progress_bar false > "$R.log" 2>&1
  echo "seed $S epoch $((E + 1)): $(grep '^| SSM' "$R/pendulum_control.md" | cut -d'|' -f3,4) $(date -u +%FT%H:%MZ)" \
    | tee -a "$OUT/scores.txt"
done
