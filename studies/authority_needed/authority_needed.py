"""How much of the torque's authority a swing-up planner needs: the true model with its torque scaled.

Run from the repository root::

    python studies/authority_needed/authority_needed.py [--scales 1,1 0.3,0.6 0,0.6 ...] [--config configs/pendulum_true_control.yaml]
        [--episodes 20] [--out studies/authority_needed/authority_needed.md]

The controller of ``--config`` (MPPI on the true model, the true state read; the plant is the Pinocchio simulator)
plans on the pendulum's own equations with the torque multiplied by ``s_up`` within ``--within`` rad of upright and
by ``s_else`` elsewhere (``--scales s_up,s_else``): a model that knows gravity exactly and the torque's effect to the
ratio that ``studies/torque_authority/torque_authority.py`` measures of a learned model (1: right; 0: no effect; below 0: the
wrong way). Each pair runs the config's episodes; the table gives the success rate and the final error. It says
which authority profile a learned model must reach before its closed loop can succeed, apart from its estimator.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from experiments.configs import load_config  # noqa: E402
from ssm_ms.control.cost import upright_error  # noqa: E402
from studies.control_diagnosis.control_diagnosis import closed_loop, episodes  # noqa: E402

DEFAULT_SCALES = ("1,1", "0.3,0.6", "0.1,0.6", "0,0.6", "-0.27,0.9", "1,0.3")


class ScaledTorque(torch.nn.Module):
    """``f(x, u * s(x))`` with ``s = s_up`` where the angle ``x[:, 0]`` is within ``within`` rad of upright, else
    ``s_else``: a transition that believes the torque does ``s`` times what ``f`` says."""

    def __init__(self, f: torch.nn.Module, s_up: float, s_else: float, within: float = 0.5):
        super().__init__()
        self.f, self.s_up, self.s_else, self.within = f, float(s_up), float(s_else), float(within)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        near = upright_error(x[:, 0]) < self.within
        scale = torch.where(near, self.s_up, self.s_else).to(u.dtype)
        return self.f(x, u * scale[:, None])


def pair(text: str) -> tuple[float, float]:
    try:
        up, other = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a scale pair is s_up,s_else (e.g. 0.3,0.6), got {text!r}") from None
    return up, other


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scales", nargs="+", type=pair, default=[pair(s) for s in DEFAULT_SCALES])
    parser.add_argument("--within", type=float, default=0.5, help="rad from upright where s_up applies")
    parser.add_argument("--config", default="configs/pendulum_true_control.yaml")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--out", default="studies/authority_needed/authority_needed.md")
    opts = parser.parse_args(argv)
    if not Path(opts.config).is_file():
        sys.exit(f"no config at {opts.config}: give a closed-loop config (e.g. configs/pendulum_true_control.yaml)")
    config = load_config(opts.config)
    starts = config["data"].get("init_args", {}).get("n_test")
    if opts.episodes < 1 or (starts is not None and opts.episodes > starts):
        sys.exit(f"--episodes must be 1 to {starts} (the starts of {opts.config}'s test split), got {opts.episodes}")
    rows = [
        f"| torque scale within {opts.within:g} rad of upright | elsewhere | success | final error (rad) |",
        "|---:|---:|---:|---:|",
    ]
    loop, dm = closed_loop(config, true_model=True)
    true_f = loop.f
    for s_up, s_else in opts.scales:
        torch.manual_seed(0)
        loop.f = ScaledTorque(true_f, s_up, s_else, opts.within)  # each episode batch resets the simulator
        _, _, final, success = loop.judge(torch.from_numpy(episodes(loop, dm, opts.episodes)[2]))
        rows.append(f"| {s_up:g} | {s_else:g} | {int(success.sum())}/{len(success)} | {final.mean():.3f} |")
        print(rows[-1], flush=True)
    lines = [
        "# How much torque authority the swing-up planner needs",
        "",
        *provenance("studies/authority_needed/authority_needed.py", argv),
        f"- The controller of `{opts.config}` plans on the pendulum's true equations and reads the true state, with "
        "the torque's effect scaled as in each row (the ratio studies/torque_authority/torque_authority.py measures of a learned "
        "model); the plant is the true simulator. Success: within "
        f"{loop.tolerance:g} rad of upright over the last {loop.success_seconds:g} s of {loop.seconds:g} s; final "
        "error: the mean distance from upright over that window.",
        "",
        *rows,
        "",
    ]
    write(opts.out, lines)


if __name__ == "__main__":
    main()
