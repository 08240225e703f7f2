"""Does an amortised-node model's sample of 256 training states (``STATE_SAMPLE``) limit the planner's distilled angle
readout? The readout fitted on the rollouts of the kept states (what the closed loop does) and on the rollouts of every
node the model encodes from its training windows, both scored on held-out rollouts of the latter (2,000 nodes, another
draw of torques). Run from the repository root:
    python studies/ukf_in_the_loop/readout_sample_try.py runs/pendulum_torque_image_nodes/<version>/checkpoints/last.ckpt
"""

import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "studies" / "control_diagnosis"))
from control_diagnosis import closed_loop  # noqa: E402

from experiments.configs import build_datamodule, load_config  # noqa: E402
from ssm_ms.control.goals import DistilledFeatures  # noqa: E402
from ssm_ms.control.module import excited_states  # noqa: E402

MAX_STATES = 200_000  # states the readout is fitted on at most (a random subset beyond)


def main(checkpoint: str) -> None:
    loop, _ = closed_loop(load_config(ROOT / "configs/pendulum_torque_control.yaml"), ssm_checkpoint=checkpoint)
    dm = build_datamodule(load_config(ROOT / "configs/pendulum_torque.yaml"))
    dm.prepare_data()
    dm.setup("fit")
    with torch.no_grad():
        encoded = torch.cat(
            [loop.ssm.encode_nodes(b["y"], b.get("u")).reshape(-1, loop.ssm.state_dim) for b in dm.train_dataloader()]
        )
    limit = max(abs(loop.settings.u_min), abs(loop.settings.u_max))
    target = loop.drawn_angle

    draw = torch.Generator().manual_seed(123)
    held = excited_states(
        loop.f, encoded[torch.randperm(len(encoded), generator=draw)[:2000]], 25, limit, loop.frame_dt, draw
    )
    held_target = torch.cat([target(part) for part in held.split(4096)])
    for name, nodes in (("the kept states", loop.ssm.training_states()), ("every encoded node", encoded)):
        states = excited_states(loop.f, nodes, 25, limit, loop.frame_dt, torch.Generator().manual_seed(0))
        if len(states) > MAX_STATES:
            states = states[torch.randperm(len(states), generator=torch.Generator().manual_seed(1))[:MAX_STATES]]
        net, own = DistilledFeatures.fit(states, target, steps=2000, seed=0)
        with torch.no_grad():
            error = float((net(held) - held_target).pow(2).mean())
        print(
            f"{name}: {len(nodes)} nodes, {len(states)} states; own held-out MSE {own:.4f}, on the held-out rollouts {error:.4f}"
        )


if __name__ == "__main__":
    main(sys.argv[1])
