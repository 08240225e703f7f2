"""The forecasting protocol's scores (``ssm_ms.forecasting.metrics``) against hand computations: MSE, BCE, the
per-frame summed MSE, SSIM by a loop over windows, the split of a sequence, and the summary over sequences."""

import math

import pytest
import torch

from ssm_ms.forecasting.metrics import (
    bce_per_sequence,
    mse_per_sequence,
    mse_sum_per_sequence,
    sequence_metrics,
    sequence_summary,
    split_sequence,
    ssim_per_sequence,
)


def test_mse_and_bce_against_hand_computation():
    torch.manual_seed(0)
    pred = torch.rand(3, 4, 1, 2, 2, dtype=torch.float64) * 0.98 + 0.01
    target = torch.rand(3, 4, 1, 2, 2, dtype=torch.float64)
    for b in range(3):
        se, bce_mean, bce_sum = 0.0, 0.0, 0.0
        for t in range(4):
            frame_bce = 0.0
            for i in range(2):
                for j in range(2):
                    p, q = pred[b, t, 0, i, j].item(), target[b, t, 0, i, j].item()
                    se += (p - q) ** 2
                    frame_bce += -(q * math.log(p + 1e-12) + (1 - q) * math.log(1 - p + 1e-12))
            bce_mean += frame_bce / 4
            bce_sum += frame_bce
        assert mse_per_sequence(pred, target)[b].item() == pytest.approx(se / 16)
        assert bce_per_sequence(pred, target, "mean")[b].item() == pytest.approx(bce_mean / 4)
        assert bce_per_sequence(pred, target, "sum")[b].item() == pytest.approx(bce_sum / 4)


def test_mse_summed_over_a_frame_against_hand_computation():
    torch.manual_seed(1)
    pred, target = torch.rand(2, 3, 1, 2, 3, dtype=torch.float64), torch.rand(2, 3, 1, 2, 3, dtype=torch.float64)
    for b in range(2):
        frames = [
            sum((pred[b, t, 0, i, j].item() - target[b, t, 0, i, j].item()) ** 2 for i in range(2) for j in range(3))
            for t in range(3)
        ]
        assert mse_sum_per_sequence(pred, target)[b].item() == pytest.approx(sum(frames) / 3)


def naive_ssim(a: list, b: list, k: int = 11, sigma: float = 1.5) -> float:
    """Wang et al.'s SSIM of two grey frames by loops: Gaussian-weighted means, variances and covariance over every
    window position that lies inside the frame, ``C1 = 0.01^2``, ``C2 = 0.03^2`` (data range 1), averaged."""
    r = k // 2
    g = [math.exp(-((i - r) ** 2) / (2 * sigma**2)) for i in range(k)]
    g = [v / sum(g) for v in g]
    h, w = len(a), len(a[0])
    values = []
    for i in range(r, h - r):
        for j in range(r, w - r):
            m = {"a": 0.0, "b": 0.0, "aa": 0.0, "bb": 0.0, "ab": 0.0}
            for u in range(k):
                for v in range(k):
                    wt, pa, pb = g[u] * g[v], a[i - r + u][j - r + v], b[i - r + u][j - r + v]
                    m["a"] += wt * pa
                    m["b"] += wt * pb
                    m["aa"] += wt * pa * pa
                    m["bb"] += wt * pb * pb
                    m["ab"] += wt * pa * pb
            va, vb, cab = m["aa"] - m["a"] ** 2, m["bb"] - m["b"] ** 2, m["ab"] - m["a"] * m["b"]
            values.append(
                (2 * m["a"] * m["b"] + 1e-4)
                * (2 * cab + 9e-4)
                / ((m["a"] ** 2 + m["b"] ** 2 + 1e-4) * (va + vb + 9e-4))
            )
    return sum(values) / len(values)


def test_ssim_against_a_loop_over_windows():
    torch.manual_seed(2)
    target = torch.rand(2, 2, 1, 13, 14, dtype=torch.float64)
    pred = (target + 0.3 * torch.randn_like(target)).clamp(0, 1)
    got = ssim_per_sequence(pred, target)
    for b in range(2):
        frames = [naive_ssim(pred[b, t, 0].tolist(), target[b, t, 0].tolist()) for t in range(2)]
        assert got[b].item() == pytest.approx(sum(frames) / 2, rel=1e-9)
    assert 0.2 < got.min() < got.max() < 0.95  # a noisy copy: neither identical nor unrelated
    assert ssim_per_sequence(target, target).tolist() == pytest.approx([1.0, 1.0])
    assert sequence_metrics(pred, target, ["ssim", "mse_sum"], "mean")["ssim"].tolist() == got.tolist()


def test_ssim_refuses_frames_it_cannot_score():
    with pytest.raises(
        ValueError, match="metric 'ssim' needs image frames .* at least 11 x 11 pixels, got \\[2, 5, 3\\]"
    ):
        ssim_per_sequence(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3))


def test_bce_of_saturated_predictions_is_finite():
    pred = torch.tensor([[[0.0, 1.0]]])
    target = torch.tensor([[[1.0, 0.0]]])
    assert bce_per_sequence(pred, target).item() == pytest.approx(-math.log(1e-12))


def test_filter_lengths_longer_than_the_sequences_are_refused():
    y = torch.zeros(2, 20, 1)
    assert [t.shape[1] for t in split_sequence(y, 15)] == [15, 5]
    assert [t.shape[1] for t in split_sequence(y, 10, 4)] == [10, 4]
    with pytest.raises(ValueError, match="cannot filter 20 and predict 0 frames of sequences of length 20"):
        split_sequence(y, 20)
    with pytest.raises(ValueError, match="cannot filter 15 and predict 10 frames of sequences of length 20"):
        split_sequence(y, 15, 10)


def test_sequence_summary_leaves_diverged_sequences_out_and_counts_them():
    scores = [0.5, float("nan"), 1.5, float("inf"), 4.0]
    finite = [0.5, 1.5, 4.0]
    mean = sum(finite) / 3
    got = sequence_summary(torch.tensor(scores))
    assert (got["n"], got["non_finite"]) == (5, 2)
    assert got["mean"] == pytest.approx(mean)
    assert got["std"] == pytest.approx(math.sqrt(sum((v - mean) ** 2 for v in finite) / 3))
    none = sequence_summary(torch.full((3,), float("nan")))
    assert (none["n"], none["non_finite"]) == (3, 3) and math.isnan(none["mean"])
