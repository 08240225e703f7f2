"""Tests of fit_by_speed.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/fit_by_speed`."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_fit_by_speed_scores_each_frame_of_each_piece_as_a_naive_loop():
    """fit_by_speed.py: each frame's error of the pieces rolled out from their nodes under their inputs."""
    from types import SimpleNamespace

    from ssm_ms.module import MultipleShootingModule
    from ssm_ms.nets import LinearReadout, LocallyLinearTransition
    from studies.fit_by_speed.fit_by_speed import errors_by_frame

    torch.manual_seed(0)
    ssm = MultipleShootingModule(
        LocallyLinearTransition(2, 2, 4, input_dim=1), LinearReadout(2, 3), state_dim=2, num_trajectories=3, n_nodes=2
    )
    clean, u, state = torch.rand(3, 10, 3), torch.randn(3, 10, 1), torch.randn(3, 10, 2)
    items = [{"y_clean": clean[i], "u": u[i], "state": state[i]} for i in range(3)]
    dm = SimpleNamespace(datasets={"train": items}, n_links=1)
    err, empty, speed = errors_by_frame(ssm, dm, 3)
    nodes = ssm.nodes.weight.detach().view(3, 2, 2)
    with torch.no_grad():
        for i in range(3):
            for j in range(2):
                x = nodes[i, j][None]
                for k in range(5):
                    t = 5 * j + k
                    assert err[i, t] == pytest.approx((ssm.g(x)[0] - clean[i, t]).pow(2).mean().item(), rel=1e-5)
                    x = ssm.f(x, u[i, t][None])
    np.testing.assert_allclose(empty, clean.pow(2).mean(2).numpy(), rtol=1e-6)
    np.testing.assert_allclose(speed, state[..., 1].abs().numpy())
