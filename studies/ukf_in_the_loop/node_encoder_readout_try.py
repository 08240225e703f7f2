"""Point 16: an amortised-node model's own node encoder as the closed loop's estimator, and how far the planner's angle
readout of its states is from the true angle along the episodes (and how far the pendulum turns). The state at frame
t+1 is the encoder's reading of the frames t-H+1..t and torques t-H+1..t (node_encoder_try.py's estimator: a node read
from the samples before it, as in training; before H frames exist the first frame is repeated with no torque). Run from the repository root:
    python studies/ukf_in_the_loop/node_encoder_readout_try.py pretrained/pendulum_torque_amortised.ckpt 20
(the tuning starts: data and loop seed 10; further arguments go to the command line of the control config)."""

import sys

import torch
from node_encoder_try import NodeEncoderEstimator

from ssm_ms.cli import main

ckpt, n = sys.argv[1], int(sys.argv[2])
args = ["--config", "configs/pendulum_torque_amortised_control.yaml", "--model.init_args.ssm_checkpoint", ckpt]
args += ["--trainer.logger", "false", "--data.init_args.seed", "10", "--model.init_args.seed", "10"]
cli = main([*args, "--data.init_args.n_test", str(n), *sys.argv[3:]], run=False)
loop, dm = cli.model, cli.datamodule
dm.setup("test")
loop.attach(dm)
estimates = []


class Recorded(NodeEncoderEstimator):  # node_encoder_try.py's estimator, each estimate kept
    def start(self, y):
        estimates.append(super().start(y))
        return estimates[-1]

    def next(self, u, y):
        estimates.append(super().next(u, y))
        return estimates[-1]


loop.estimator = lambda: Recorded(loop.ssm.node_encoder.eval(), loop.to_frames, loop.to_inputs)
starts = torch.cat([b["state"][:, 0] for b in dm.test_dataloader()]).double().numpy()
with torch.no_grad():
    run = loop.episodes(starts)
    x = torch.stack(estimates, 1)
    read = loop.features(x.reshape(-1, x.shape[-1])).reshape(*x.shape[:2], 2)
true = run["states"][:, :, 0].float()
_, _, final, ok = loop.judge(true)
off = torch.atan2(read[..., 0], read[..., 1]) - true
off = torch.atan2(torch.sin(off), torch.cos(off))
print(f"node encoder as the estimator: {int(ok.sum())}/{len(ok)} up, final error {float(final.mean()):.3f} rad")
print(f"readout vs true angle (RMS, rad): first 20 steps {float(off[:, :20].pow(2).mean().sqrt()):.3f}, after")
print(f"  {float(off[:, 20:].pow(2).mean().sqrt()):.3f}; largest |true angle| per episode (rad):")
print(" ", [round(float(a), 1) for a in true.abs().max(1).values])
