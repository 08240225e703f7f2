"""The valid prediction time's accumulator (``ssm_ms.forecasting.valid_time``) against hand computations: the
pooled variance of images, the error growth without a diverged forecast, the floor of images' reconstruction
error, and a batch of forecasts cut into what is scored."""

import math

import pytest
import torch

from ssm_ms.forecasting.analysis_settings import ValidTimeSettings
from ssm_ms.forecasting.valid_time import ValidTimeAccumulator, valid_time_split


def test_valid_time_of_images_scales_by_the_mean_per_pixel_variance():
    """Images pool their pixels: mean squared error over the mean per-pixel variance of the truth, so a
    forecast as bad as the mean frame has normalised error 1; constant background pixels divide nothing."""
    torch.manual_seed(0)
    truth = torch.rand(2, 3, 6, 1, 2, 2, dtype=torch.float64)  # two batches of 3 sequences, 6 steps
    truth[..., 0, 0] = 0.0  # a background pixel
    growth = torch.linspace(0.0, 1.0, 6, dtype=torch.float64).view(1, 1, 6, 1, 1, 1)  # errors grow over time,
    size = torch.tensor([0.02, 0.1, 0.2, 0.3, 0.4, 0.6], dtype=torch.float64).view(2, 3, 1, 1, 1, 1)  # more or less
    pred = truth + torch.randn_like(truth) * growth * size
    acc = ValidTimeAccumulator()
    for b in range(2):
        acc.update(pred[b], truth[b])
    steps, horizon = acc.steps(0.5)
    all_truth = truth.reshape(6, 6, 4)  # [sequence, step, pixel]
    pixel_var = all_truth.reshape(-1, 4).var(0, unbiased=False).mean()
    expected = []
    for seq_pred, seq_truth in zip(pred.reshape(6, 6, 4), all_truth):
        err = ((seq_pred - seq_truth) ** 2).mean(1) / pixel_var
        expected.append(next((t for t in range(6) if err[t].sqrt() > 0.5), math.inf))
    assert horizon == 6 and steps.tolist() == expected
    curve = torch.stack(
        [(((sp - st) ** 2).mean(1) / pixel_var).sqrt() for sp, st in zip(pred.reshape(6, 6, 4), all_truth)]
    )
    assert acc.growth() == pytest.approx({"1": 0.0, "3": curve[:, 2].mean().item(), "6": curve[:, 5].mean().item()})
    assert 0 < sum(e != math.inf for e in expected) < 6  # the case is not trivial


def test_error_growth_leaves_out_a_diverged_forecast():
    """A forecast that turned NaN (a filter that diverged) is left out of the mean error curve, as out of the
    scores; the others' curve is their plain mean of |error| / std (vectors: per component, then averaged)."""
    torch.manual_seed(1)
    truth = torch.randn(4, 8, 2, dtype=torch.float64)
    pred = truth + 0.1 * torch.randn_like(truth) * torch.arange(1, 9, dtype=torch.float64).view(1, 8, 1)
    pred[2, 5:] = math.nan
    acc = ValidTimeAccumulator()
    acc.update(pred[:2], truth[:2])
    acc.update(pred[2:], truth[2:])
    std = truth.reshape(-1, 2).std(0, unbiased=False)
    kept = [0, 1, 3]
    curve = [sum(((pred[i, t] - truth[i, t]) ** 2 / std**2).mean().sqrt().item() for i in kept) / 3 for t in range(8)]
    assert acc.growth() == pytest.approx({"1": curve[0], "2": curve[1], "4": curve[3], "8": curve[7]})
    assert acc.steps(10.0)[0].tolist() == [math.inf, math.inf, 5, math.inf]  # still counted, invalid from its NaN


def test_valid_time_of_images_counts_the_error_above_the_reconstruction_floor():
    """A forecaster whose decoder blurs every frame by the same amount (its reconstruction of the given frames
    included) and loses the object after s steps: valid for exactly s steps, counted by hand above its floor;
    without the given frames the blur alone reads as invalid from the first step."""
    torch.manual_seed(1)
    n, h, m = 5, 12, 4
    truth = (torch.rand(n, m + h, 1, 6, 6, dtype=torch.float64) > 0.7).double()  # sparse "lit" pixels
    blur = 0.4 * torch.randn(n, 1, 1, 6, 6, dtype=torch.float64)  # the decoder's error, the same on every frame
    lost = torch.tensor([0, 3, 7, 11, 12])  # step at which each sequence's forecast loses the object
    est = truth + blur
    for i, s in enumerate(lost.tolist()):
        est[i, m + s :] = truth[i, m + s :].roll(3, dims=-1) + blur[i]  # drawn elsewhere, same blur
    acc = ValidTimeAccumulator()
    acc.update(est[:, m:], truth[:, m:], given=(est[:, :m], truth[:, :m]))
    steps, horizon = acc.steps(0.5)
    # by hand: pooled variance, per-sequence floor from the given frames, error above it, first step over 0.5
    values = truth[:, m:].reshape(-1, 36)
    var = values.var(0, unbiased=False).mean()
    expected = []
    for i in range(n):
        floor = ((est[i, :m] - truth[i, :m]) ** 2).mean()
        err = [(((est[i, m + t] - truth[i, m + t]) ** 2).mean() - floor).clamp_min(0).div(var).sqrt() for t in range(h)]
        expected.append(next((t for t in range(h) if err[t] > 0.5), math.inf))
    assert horizon == h and steps.tolist() == expected
    assert expected[1:] == [3.0, 7.0, 11.0, math.inf] and expected[0] == 0.0  # as constructed
    assert acc.floor() == pytest.approx(
        float(((est[:, :m] - truth[:, :m]) ** 2).flatten(1).mean(1).div(var).sqrt().mean())
    )
    assert acc.floor() > 0.5  # the blur alone is over the threshold:
    plain = ValidTimeAccumulator()
    plain.update(est[:, m:], truth[:, m:])
    assert plain.steps(0.5)[0].tolist() == [0.0] * n and plain.floor() == 0.0


def test_a_batch_of_forecasts_is_cut_into_the_forecast_and_the_floor_frames():
    """``add_forecast`` scores the ``h`` predicted steps against the truth after the ``k`` given ones, in the units
    ``to_units`` gives, with the last 10 given frames as the floor; by hand with :meth:`update` on slices cut here."""
    torch.manual_seed(3)
    k, h = 12, 5
    truth = torch.rand(3, k + h + 2, 1, 4, 4, dtype=torch.float64)  # longer than k + h: the rest is not scored
    filtered = truth[:, :k] + 0.1 * torch.randn(3, k, 1, 4, 4, dtype=torch.float64)
    predicted = truth[:, k : k + h] + 0.3 * torch.randn(3, h, 1, 4, 4, dtype=torch.float64)
    acc = ValidTimeAccumulator()
    acc.add_forecast(filtered, predicted, truth, clean=False, to_units=lambda t: 2.0 * t + 1.0)
    by_hand = ValidTimeAccumulator()
    by_hand.update(
        2 * predicted + 1,
        2 * truth[:, 12:17] + 1,
        clean=False,
        given=(2 * filtered[:, 2:12] + 1, 2 * truth[:, 2:12] + 1),
    )
    torch.testing.assert_close(acc.normalised_errors(), by_hand.normalised_errors())
    assert acc.floor() == pytest.approx(by_hand.floor()) and not acc.clean


def test_the_valid_time_split_falls_back_to_the_protocols():
    assert valid_time_split(ValidTimeSettings(n_filter=1000, horizon=1000), 1990, 10, 2000) == (1000, 1000)
    assert valid_time_split(ValidTimeSettings(), 50, None, 100) == (50, 50)  # the protocol's split: the rest
    assert valid_time_split(ValidTimeSettings(), 50, 20, 100) == (50, 20)
    assert valid_time_split(ValidTimeSettings(n_filter=30), 50, None, 100) == (30, 70)


def test_several_sensors_are_normalised_stream_by_stream_and_weigh_the_same():
    """A packed camera-and-angle measurement (an image of 3x3 pixels, one of them always dark, and a 2-vector):
    each stream normalised on its own (the image pooled above its floor, the vector per component), the step's
    error the root mean square of the two; a missing angle sample leaves the image alone to judge that step. The
    packed vector read as one vector instead divides by the dark pixel's zero variance."""
    from ssm_ms.nets.sensors import SensorLayout, Stream

    torch.manual_seed(4)
    layout = SensorLayout([Stream("image", (1, 3, 3), 0.2), Stream("angle", (2,), 0.05)])
    n, k, h = 4, 10, 6
    image = torch.rand(n, k + h, 9, dtype=torch.float64)
    image[..., 0] = 0.0  # a pixel that never lights
    angle = torch.randn(n, k + h, 2, dtype=torch.float64)
    truth = torch.cat([image, angle], -1)
    estimate = truth + 0.05 * torch.randn_like(truth)
    grow = torch.linspace(0.1, 1.5, h, dtype=torch.float64).view(1, h, 1)
    predicted = truth[:, k:] + grow * torch.randn(n, h, 11, dtype=torch.float64)
    truth[1, k + 2, 9:] = math.nan  # the angle not sampled at that step
    acc = ValidTimeAccumulator(layout)
    acc.add_forecast(estimate[:, :k], predicted, truth, clean=True)

    pixel_var = image[:, k:].reshape(-1, 9).var(0, unbiased=False).mean()
    seen = truth[:, k:, 9:].reshape(-1, 2)
    seen = seen[~seen.isnan().any(1)]
    angle_var = seen.var(0, unbiased=False)
    expected = torch.empty(n, h, dtype=torch.float64)
    for i in range(n):
        floor = ((estimate[i, :k, :9] - truth[i, :k, :9]) ** 2)[-10:].mean()
        for t in range(h):
            e_image = (((predicted[i, t, :9] - truth[i, k + t, :9]) ** 2).mean() - floor).clamp_min(0) / pixel_var
            e_angle = ((predicted[i, t, 9:] - truth[i, k + t, 9:]) ** 2 / angle_var).mean()
            expected[i, t] = e_image.sqrt() if e_angle.isnan() else ((e_image + e_angle) / 2).sqrt()
    torch.testing.assert_close(acc.normalised_errors(), expected)
    steps, horizon = acc.steps(0.5)
    by_hand = [next((t for t in range(h) if row[t] > 0.5), math.inf) for row in expected]
    assert horizon == h and steps.tolist() == by_hand and acc.count == n * h
    assert any(0 < s < h for s in by_hand)  # the case is not trivial
    floors = [((estimate[i, :k, :9] - truth[i, :k, :9]) ** 2)[-10:].mean() for i in range(n)]
    assert acc.floor() == pytest.approx(float(sum((f / pixel_var).sqrt() for f in floors) / n))
    packed = ValidTimeAccumulator()
    packed.add_forecast(estimate[:, :k], predicted, truth, clean=True)
    assert packed.normalised_errors()[0, 0] > 1e6  # the dark pixel's variance, clamped to 1e-30
