"""Tests of control_diagnosis.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/control_diagnosis`."""

import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_control_diagnosis_reads_the_filter_and_its_k_step_predictions_as_a_naive_loop():
    """control_diagnosis.py: the angle of each filtered state, and of f applied k times to it under the
    torques that followed, at the frame it predicts; the table's bands by the true angle's distance from upright."""
    from types import SimpleNamespace

    from ssm_ms.control.estimators import UKFEstimator
    from ssm_ms.inference.ukf import UnscentedKalmanFilter
    from studies.control_diagnosis import control_diagnosis as D

    torch.manual_seed(0)
    a, b = torch.tensor([[0.9, 0.2], [-0.3, 0.8]]), torch.tensor([[0.5], [-0.1]])

    def f(x, u):
        return x @ a.T + u @ b.T

    def g(x):
        return torch.cat([x, x.sum(1, keepdim=True)], 1)

    def features(x):
        return torch.stack([torch.sin(x[:, 0]), torch.cos(x[:, 0])], 1)

    ukf = UnscentedKalmanFilter(f, g, process_var=1e-2, measurement_var=0.1, init_var=1.0, state_dim=2)
    loop = SimpleNamespace(estimator=lambda: UKFEstimator(ukf, torch.zeros(2), lambda y: y), features=features, f=f)
    frames, inputs = [torch.randn(3, 3) for _ in range(7)], torch.randn(3, 6, 1)
    read, ahead = D.diagnose(loop, frames, inputs)
    assert np.isnan(ahead[5][:, :5]).all()  # no prediction before k frames
    mean = torch.zeros(3, 2)
    cov = ukf.initial_covariance(3, 2, mean.dtype, mean.device)
    mean, cov = ukf.update(mean, cov, frames[0])
    means = [mean]
    for t in range(6):
        mean, cov = ukf.update(*ukf.predict(mean, cov, inputs[:, t]), frames[t + 1])
        means.append(mean)
    for t in range(7):
        want = torch.atan2(torch.sin(means[t][:, 0]), torch.cos(means[t][:, 0]))
        np.testing.assert_allclose(read[:, t], want.double().numpy(), atol=1e-6)
        for k in D.STEPS:
            if t + k > 6:  # past the last frame
                continue
            x = means[t]
            for j in range(k):
                x = f(x, inputs[:, t + j])
            want = torch.atan2(torch.sin(x[:, 0]), torch.cos(x[:, 0]))
            np.testing.assert_allclose(ahead[k][:, t + k], want.double().numpy(), atol=1e-5)
    assert np.isnan(ahead[10]).all()  # 10 steps ahead of 7 frames: nothing
    truth = np.array([[np.pi, 0.0, 2.0, np.pi - 0.2]])  # upright, hanging, 1.14 from upright, upright
    nan = np.full_like(truth, np.nan)
    nan[0, 0] = truth[0, 0] + 0.3  # a column with one frame: the mean of the band's frames it has
    rows = D.table(truth, {"a": truth + 0.1, "b": truth - 0.2, "c": nan})
    assert rows[0] == "| true angle from upright (rad) | share of frames | a | b | c |"
    assert rows[2] == "| 0 to 0.5 | 0.50 | 0.100 | 0.200 | 0.300 |"
    assert rows[3].startswith("| 0.5 to 1.5 | 0.25 |") and rows[5].startswith("| 2.5 and above | 0.25 |")
    assert rows[6] == "| all frames | 1.00 | 0.100 | 0.200 | 0.300 |"  # every frame's error, the frames it has
