"""How well a trained pendulum SSM draws its training trajectories, by how fast the pendulum moves; writes a table.

Run from the repository root::

    python studies/fit_by_speed/fit_by_speed.py --ssm-checkpoint runs/pendulum_torque/<version>/checkpoints/last.ckpt \\
        [--config configs/pendulum_torque.yaml] [--trajectories 100] [--out studies/fit_by_speed/fit_by_speed.md]

Each of the first ``--trajectories`` training trajectories is rolled out piece by piece from its own shooting nodes
under its own inputs (what the shooting loss fits), decoded by ``g``, and each frame's squared error against the
noiseless frame is binned by the true angular speed ``|q'|`` of the first joint at that frame. Beside it, the error
of predicting zeros (an empty frame), which a model that has not learned a regime can fall behind. ``--config`` is
the config the SSM was trained with (its data section is read; the normalisation comes from the checkpoint).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance  # noqa: E402
from datamodules.pendulum import PendulumDataModule  # noqa: E402
from experiments.configs import load_config  # noqa: E402
from ssm_ms.checkpointing import datamodule_state  # noqa: E402
from ssm_ms.loading import load_ssm  # noqa: E402
from ssm_ms.training.shooting import rollout  # noqa: E402

BANDS = ((0.0, 2.0), (2.0, 4.0), (4.0, 6.0), (6.0, float("inf")))  # rad/s


def errors_by_frame(ssm, dm: PendulumDataModule, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(model error, empty-frame error, speed)``, each ``[count, T]``: per frame, the clean-frame MSE of the pieces'
    rollouts from their nodes, that of an empty frame, and ``|q'|`` of the first joint."""
    ds = dm.datasets["train"]
    items = [ds[i] for i in range(count)]
    clean = torch.stack([it["y_clean"] for it in items]).flatten(2)
    u = torch.stack([it["u"] for it in items]) if "u" in items[0] else None
    speed = np.abs(np.stack([it["state"][:, dm.n_links].numpy() for it in items]))
    nodes = ssm.nodes.weight.detach().view(ssm.nodes.weight.shape[0], -1, ssm.state_dim)[:count]
    pieces, t = nodes.shape[1], clean.shape[1]
    n = t // pieces
    err = []
    with torch.no_grad():
        for j in range(pieces):
            inputs = None if u is None else u[:, j * n : (j + 1) * n - 1]
            states = rollout(ssm.f, nodes[:, j], n, inputs)
            drawn = ssm.g(states.reshape(-1, ssm.state_dim)).view(count, n, -1)
            err.append((drawn - clean[:, j * n : (j + 1) * n]).pow(2).mean(2))
    return torch.cat(err, 1).numpy(), clean.pow(2).mean(2).numpy(), speed


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ssm-checkpoint", required=True, help="a trained pendulum SSM (last.ckpt)")
    parser.add_argument("--config", default="configs/pendulum_torque.yaml", help="the config it was trained with")
    parser.add_argument("--trajectories", type=int, default=100, help="training trajectories scored")
    parser.add_argument("--data-dir", default="data", help="where the data are cached")
    parser.add_argument("--out", default="studies/fit_by_speed/fit_by_speed.md")
    args = parser.parse_args(argv)
    ckpt = Path(args.ssm_checkpoint)
    if not ckpt.is_file():
        sys.exit(
            f"no SSM checkpoint at {ckpt}: train one first (python cli.py fit --config configs/pendulum_torque.yaml)"
        )
    ssm, saved = load_ssm(ckpt)
    data = load_config(ROOT / args.config)["data"]
    if data.get("class_path") != "datamodules.pendulum.PendulumDataModule":
        sys.exit(f"{args.config}: its data are not the pendulum's ({data.get('class_path')}); give a pendulum config")
    init = {**data["init_args"], "data_dir": args.data_dir}
    dm = PendulumDataModule(**init)
    state = datamodule_state(saved)
    if state is not None:
        dm.load_state_dict(state[1])
    dm.prepare_data()
    dm.setup("fit")
    count = min(args.trajectories, ssm.nodes.weight.shape[0])
    err, empty, speed = errors_by_frame(ssm, dm, count)
    lines = [
        "# A pendulum SSM's fit of its training trajectories, by angular speed (one run)",
        "",
        *provenance("studies/fit_by_speed/fit_by_speed.py", argv),
        f"- Data: those of `{args.config}`, the first {count} training trajectories; each piece rolled out from its own "
        "node under its own inputs, decoded by g; mean squared error per frame against the noiseless frame.",
        "",
        "| angular speed (rad/s) | share of frames | model | zeros (an empty frame) | model / zeros |",
        "|---|---:|---:|---:|---:|",
    ]
    for lo, hi in BANDS:
        m = (speed >= lo) & (speed < hi)
        if not m.any():
            continue
        band = f"{lo:g} to {hi:g}" if np.isfinite(hi) else f"{lo:g} and above"
        lines.append(
            f"| {band} | {m.mean():.2f} | {err[m].mean():.4f} | {empty[m].mean():.4f} | "
            f"{err[m].mean() / empty[m].mean():.2f} |"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines[-len(BANDS) - 2 :]))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
