#!/bin/bash
# Copy a carried run's resumable state from runs/ into carry/ (after it stopped cleanly: `kill <reproduce pid>`):
# for each stage folder named here that has a checkpoint, its last completed epoch's last.ckpt, its config and the
# run's record (reproduce.json, in the first stage's folder); its TensorBoard event files only with CARRY_EVENTS=1
# (a Lorenz fit logging every step writes ~75 KB an epoch: each commit would add the whole file again). Prints each
# stage's epochs; then `git add -f carry/` (*.ckpt is ignored) and commit.
#   carry/update.sh lorenz_T1000/reproduce-20261129-133138 [more stage/version folders]
set -e
cd "$(dirname "$0")/.."
[ $# -gt 0 ] || { echo "usage: carry/update.sh <stage>/<version> ... (folders under runs/)" >&2; exit 2; }
for run in "$@"; do
  R=runs/$run
  C=carry/$run
  [ -f "$R/checkpoints/last.ckpt" ] || { echo "$run: no runs/$run/checkpoints/last.ckpt, not carried"; continue; }
  rm -rf "$C" && mkdir -p "$C/checkpoints"
  cp "$R/checkpoints/last.ckpt" "$C/checkpoints/"
  events=()
  [ "${CARRY_EVENTS:-0}" = 1 ] && events=("$R"/events.out.tfevents.*)
  for f in "$R"/config.yaml "$R"/hparams.yaml "$R"/reproduce.json "${events[@]}"; do
    [ -f "$f" ] && cp "$f" "$C/"
  done
  .venv/bin/python -c "import torch; e = torch.load('$C/checkpoints/last.ckpt', map_location='cpu', weights_only=False)['epoch']; print('$run: epoch index', e, '=', e + 1, 'epochs done')"
done
du -sh carry
