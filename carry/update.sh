#!/bin/bash
# Copy the carried run's resumable state from runs/ into carry/ (after it stopped cleanly: `kill <reproduce pid>`),
# each stage that has started: the SSM (runs/quad_1000/) and, once the SSM has finished, the encoder
# (runs/quad_1000_encoder/, only with CARRY_ENCODER=1: its checkpoint is ~57 MB; without it the encoder stage starts
# again from its epoch 0 after a move). Prints each stage's last completed epoch; then `git add -f carry/` and commit.
set -e
cd "$(dirname "$0")/.."
V=reproduce-20261128-061047
for stage in quad_1000 quad_1000_encoder; do
  R=runs/$stage/$V
  C=carry/$stage/$V
  [ -f "$R/checkpoints/last.ckpt" ] || continue
  [ "$stage" = quad_1000_encoder ] && [ "${CARRY_ENCODER:-0}" != 1 ] && { echo "$stage: not carried (CARRY_ENCODER=1 to)"; continue; }
  rm -rf "$C" && mkdir -p "$C/checkpoints"
  cp "$R/checkpoints/last.ckpt" "$C/checkpoints/"
  for f in config.yaml hparams.yaml reproduce.json "$R"/events.out.tfevents.*; do
    f=$(basename "$f")
    [ -f "$R/$f" ] && cp "$R/$f" "$C/"
  done
  .venv/bin/python -c "import torch; e = torch.load('$C/checkpoints/last.ckpt', map_location='cpu', weights_only=False)['epoch']; print('$stage: epoch index', e, '=', e + 1, 'epochs done')"
done
du -sh carry
