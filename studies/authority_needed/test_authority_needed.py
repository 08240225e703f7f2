"""Tests of authority_needed.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/authority_needed`."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_authority_needed_scales_the_torque_near_upright_and_elsewhere():
    """authority_needed.py: the true pendulum with its torque scaled by 0.5 within 0.5 rad of upright and by
    2 elsewhere turns as the linearised pendulum under the scaled torque does, 2 s tau (cosh(w t) - 1) / w^2 at upright
    and 2 s tau (1 - cos(w t)) / w^2 hanging (w = sqrt(g), from rest, one frame of 0.1 s)."""
    from ssm_ms.control.plant import TruePendulum
    from studies.authority_needed.authority_needed import ScaledTorque
    from studies.torque_authority.torque_authority import turns

    w, t, tau = np.sqrt(9.81), 0.1, 0.1
    states = torch.tensor([[np.pi + 0.01, 0.0], [0.01, 0.0]], dtype=torch.float64)  # upright, hanging
    got = turns(ScaledTorque(TruePendulum(t).double(), 0.5, 2.0), lambda z: z[:, 0].numpy(), states, 1, tau)
    want = [2 * 0.5 * tau * (np.cosh(w * t) - 1) / w**2, 2 * 2.0 * tau * (1 - np.cos(w * t)) / w**2]
    np.testing.assert_allclose(got, want, rtol=1e-3)


def test_authority_needed_refuses_more_episodes_than_starts_and_a_missing_config(tmp_path):
    from studies.authority_needed.authority_needed import main

    with pytest.raises(SystemExit, match=r"--episodes must be 1 to 20 .* got 21"):
        main(["--episodes", "21", "--out", str(tmp_path / "unused.md")])
    with pytest.raises(SystemExit, match="no config at nope.yaml"):
        main(["--config", "nope.yaml"])
