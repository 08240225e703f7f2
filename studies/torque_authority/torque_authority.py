"""What a learned pendulum SSM believes the torque does, at its own shooting nodes, against the true equations.

Run from the repository root::

    python studies/torque_authority/torque_authority.py --ssm-checkpoint runs/pendulum_torque/<version>/checkpoints/last.ckpt \\
        [--data-config configs/data/pendulum_torque.yaml] [--set closed_loop_noise=1.0] [--out FILE.md]

Every shooting node ``s_i`` of the SSM's training data is the model's state of a frame whose true state (angle,
velocity) the data set knows. From each node ``f`` runs ``--steps`` steps of the largest torque one way and, again,
the other; the angles ``g`` draws at the two ends (the angle of the ink about the pivot, as the controller reads a
frame; with several sensors, from the camera's stream) are compared, and the same is done from the true state by the
pendulum's equations. Their ratio is the model's authority of the input against the system's: 1 where the model
knows what the torque does, 0 where it believes the torque does nothing. Trajectories driven by a feedback
controller hold the torque tied to the state (closed-loop identification), so there the effect of the input can hide
in the state's: this measures it, by the true angle's distance from upright. ``--set KEY=VALUE`` changes an argument
of the data config (e.g. the exploration of a probe run's data); the SSM must have been trained on that data (the
generator's parameters saved in its checkpoint are checked).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import yaml

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from experiments.configs import build_datamodule  # noqa: E402
from ssm_ms.checkpointing import datamodule_state  # noqa: E402
from ssm_ms.control.cost import upright_error  # noqa: E402
from ssm_ms.control.goals import ink_angle_features  # noqa: E402
from ssm_ms.control.plant import TruePendulum  # noqa: E402
from ssm_ms.loading import load_ssm  # noqa: E402
from ssm_ms.nets.sensors import SensorLayout  # noqa: E402
from ssm_ms.training.shooting import decode  # noqa: E402
from studies.control_diagnosis.control_diagnosis import BANDS  # noqa: E402  (the same bands of distance from upright)


def wrapped(a: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(a), np.cos(a))


@torch.no_grad()
def turns(f, read, x0: torch.Tensor, steps: int, torque: float) -> np.ndarray:
    """``[N]``: the angle ``read`` from the state after ``steps`` steps of ``f`` under ``+torque`` minus the angle
    after as many under ``-torque``, both from ``x0 [N, d]``, wrapped to ``[-pi, pi)``."""
    ends = []
    for sign in (1.0, -1.0):
        x = x0
        for _ in range(steps):
            x = f(x, torch.full((len(x), 1), sign * torque, dtype=x.dtype))
        ends.append(read(x))
    return wrapped(ends[0] - ends[1])


@torch.no_grad()
def falls(f, read, x0: torch.Tensor, steps: int) -> np.ndarray:
    """``[N]``: how much farther from upright the angle ``read`` from the state is after ``steps`` steps of ``f``
    without torque than at ``x0`` (rad; positive: it falls away from upright, as gravity makes it there)."""
    x = x0
    for _ in range(steps):
        x = f(x, torch.zeros((len(x), 1), dtype=x.dtype))
    start, end = (upright_error(torch.as_tensor(read(z))).numpy() for z in (x0, x))
    return end - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ssm-checkpoint", required=True)
    parser.add_argument("--data-config", default="configs/data/pendulum_torque.yaml")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a data argument changed")
    parser.add_argument("--steps", type=int, default=3, help="steps of the largest torque each way")
    parser.add_argument("--torque", type=float, default=3.0, help="the largest torque (N m)")
    parser.add_argument("--out", default="studies/torque_authority/torque_authority.md")
    opts = parser.parse_args(argv)
    try:
        ssm, raw = load_ssm(opts.ssm_checkpoint)
    except (OSError, ValueError) as e:
        sys.exit(str(e))
    changes = {}
    for item in opts.set:
        key, _, value = item.partition("=")
        changes[key] = yaml.safe_load(value)
    try:
        dm = build_datamodule(opts.data_config, **changes)
    except (OSError, ValueError) as e:  # no such file, an unknown or invalid --set
        sys.exit(f"the data of {opts.data_config} with {opts.set}: {e}")
    saved = datamodule_state(raw)
    if saved is not None and saved[1]["generator_params"] != dm.generator_params():
        sys.exit(
            f"the SSM was trained on other data than {opts.data_config} with {opts.set}: give the data config and "
            "--set KEY=VALUE of its training run (e.g. --set closed_loop_noise=1.0 for a probe trained with it)"
        )
    dm.prepare_data()
    dm.setup("fit")
    if saved is not None:
        dm.load_state_dict(saved[1])  # the SSM's normalisations of frames and inputs
    data = dm.datasets["train"]
    if len(data) != ssm.nodes.num_embeddings:
        sys.exit(f"the SSM holds nodes for {ssm.nodes.num_embeddings} trajectories, the data have {len(data)}")
    items = [data[i] for i in range(len(data))]
    index = torch.tensor([int(item["index"]) for item in items])
    states = torch.stack([torch.as_tensor(item["state"]) for item in items]).double()  # [N, T, 2]
    m, d = ssm.n_nodes, ssm.state_dim
    n = states.shape[1] // m
    truth0 = states[:, ::n][:, :m].reshape(-1, 2)  # the true state at each node's frame
    with torch.no_grad():
        nodes = ssm.node_states(index).reshape(-1, d)
    to_inputs = dm.input_normalizer.normalize if dm.input_normalizer is not None else (lambda u: u)
    to_frames = dm.normalizer.denormalize if dm.normalizer is not None else (lambda y: y)

    # several sensors: the camera's stream of the packed measurement (the angle is read from the frame either way)
    camera = (lambda y: SensorLayout.from_state_dict(dm.sensor_layout).split(y)["image"]) if dm.sensor_layout else None

    @torch.no_grad()
    def drawn_angle(x: torch.Tensor) -> np.ndarray:
        frames = to_frames(decode(ssm.g, x, 4096))
        frames = camera(frames) if camera is not None else frames
        sc = ink_angle_features(frames, (frames.shape[-1] / 2, frames.shape[-2] / 2))
        return torch.atan2(sc[:, 0], sc[:, 1]).double().numpy()

    true_f = TruePendulum(dm.environment(0).frame_dt, dm.damping).double()
    model_turn = turns(lambda x, u: ssm.f(x, to_inputs(u)), drawn_angle, nodes, opts.steps, opts.torque)
    true_turn = turns(true_f, lambda z: z[:, 0].numpy(), truth0, opts.steps, opts.torque)
    model_fall = falls(lambda x, u: ssm.f(x, to_inputs(u)), drawn_angle, nodes, opts.steps)
    true_fall = falls(true_f, lambda z: z[:, 0].numpy(), truth0, opts.steps)
    readout = np.abs(wrapped(drawn_angle(nodes) - truth0[:, 0].numpy()))
    from_up = upright_error(truth0[:, 0]).numpy()
    generated = (index < dm.n_train).numpy()  # the rest: recorded episodes
    closed = np.zeros(len(index), dtype=bool)
    if dm.closed_loop_share:
        from datamodules.pendulum_excitation import closed_loop

        closed = closed_loop(index.tolist(), dm.closed_loop_share) & generated
    closed, opened = np.repeat(closed, m), np.repeat(generated & ~closed, m)

    rows = [
        "| true angle from upright (rad) | nodes | of them in closed loop | node's drawn angle error (rad) | model turn "
        "(rad) | true turn (rad) | median ratio | median ratio, closed-loop trajectories | median ratio, open-loop "
        "(generated) | model fall, no torque (rad) | true fall, no torque (rad) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    ratio = model_turn / true_turn

    def med(mask: np.ndarray) -> str:
        return f"{np.median(ratio[mask]):.2f}" if mask.any() else "-"

    for lo, hi in BANDS:
        band = (from_up >= lo) & (from_up < hi)
        label = f"{lo:g} to {hi:.1f}" if hi < np.pi else f"{lo:g} and above"
        rows.append(
            f"| {label} | {band.sum()} | {closed[band].mean():.2f} | {readout[band].mean():.3f} | "
            f"{model_turn[band].mean():.3f} | {true_turn[band].mean():.3f} | {med(band)} | {med(band & closed)} | "
            f"{med(band & opened)} | {model_fall[band].mean():.3f} | {true_fall[band].mean():.3f} |"
        )
    lines = [
        "# What a learned pendulum SSM believes the torque does, at its shooting nodes",
        "",
        *provenance("studies/torque_authority/torque_authority.py", argv),
        f"- From each of the {len(nodes)} shooting nodes, {opts.steps} steps of {opts.torque:g} N m one way against "
        "the other: how far apart the angles the decoder draws at the two ends are (model turn), beside the same from "
        "the node's true state by the true equations (true turn); ratio: model / truth (1: the model knows what the "
        "torque does; 0: it believes it does nothing). Binned by the node's true angle from upright. Closed loop: the "
        "data's trajectories driven by its swing-up-and-balance controller plus exploration (closed_loop_share); open "
        "loop: those driven by the random excitation alone; recorded episodes (recorded) count in neither. Fall: "
        f"how much farther from upright the angle is after {opts.steps} steps without torque than at the node "
        "(gravity's pull away from upright), drawn by the model and by the true equations.",
        "",
        *rows,
        "",
    ]
    write(opts.out, lines)


if __name__ == "__main__":
    main()
