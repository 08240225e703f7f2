"""Tests of torque_authority.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/torque_authority`."""

import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_torque_authority_turns_match_a_linear_systems_closed_form():
    """torque_authority.py: k steps of +tau against -tau through x+ = A x + B u, read as x[0], end
    2 tau (sum_{j<k} A^j B)[0] apart; a transition that ignores u turns nothing; the pendulum's equations about
    tau t^2 (the torque's push on a unit mass, gravity aside)."""
    from ssm_ms.control.plant import TruePendulum
    from studies.torque_authority.torque_authority import turns

    a = torch.tensor([[0.95, 0.1], [-0.2, 0.9]], dtype=torch.float64)
    b = torch.tensor([[0.03], [0.1]], dtype=torch.float64)
    x0 = torch.randn(5, 2, dtype=torch.float64) * 0.1
    got = turns(lambda x, u: x @ a.T + u @ b.T, lambda x: x[:, 0].numpy(), x0, 3, 2.0)
    want = 2 * 2.0 * (b + a @ b + a @ a @ b)[0, 0].item()
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert np.all(turns(lambda x, u: x @ a.T, lambda x: x[:, 0].numpy(), x0, 3, 2.0) == 0)
    pendulum = TruePendulum(0.1).double()
    states = torch.tensor([[np.pi - 0.1, 0.5], [0.3, -1.0]], dtype=torch.float64)
    true_turn = turns(pendulum, lambda z: z[:, 0].numpy(), states, 3, 3.0)
    np.testing.assert_allclose(true_turn, 3.0 * 0.3**2, rtol=0.1)  # gravity's pull is the same both ways, nearly


def test_torque_authority_falls_match_the_linearised_upright_pendulum():
    """Without torque, from d0 rad off upright at rest, the pendulum's distance from upright grows as d0 cosh(sqrt(g)
    t) (d'' = g d, linearised); a transition that keeps the state draws no fall."""
    from ssm_ms.control.plant import TruePendulum
    from studies.torque_authority.torque_authority import falls

    d0 = np.array([0.02, -0.05])
    states = torch.tensor(np.stack([np.pi + d0, np.zeros(2)], 1), dtype=torch.float64)
    got = falls(TruePendulum(0.1).double(), lambda z: z[:, 0].numpy(), states, 3)
    np.testing.assert_allclose(got, np.abs(d0) * (np.cosh(np.sqrt(9.81) * 0.3) - 1), rtol=0.02)
    assert np.all(falls(lambda x, u: x, lambda z: z[:, 0].numpy(), states, 3) == 0)
