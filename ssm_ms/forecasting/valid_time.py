"""The valid prediction time of a forecaster over the test set (``analysis.valid_time``), and the true system's
Lyapunov exponents that express it in Lyapunov times (``analysis.true_system``).

Each test sequence is forecast ``horizon`` steps after ``n_filter`` given ones (:func:`valid_time_split`); the
forecast is valid while its normalised error against the noiseless truth stays <= the threshold (0.5, the
reservoir-computing convention of Vlachas et al. 2020). :class:`ValidTimeAccumulator` collects the errors over
the test batches and :meth:`ValidTimeAccumulator.report` summarises them for the results file, in steps,
seconds and Lyapunov times of the true system (:func:`reference_exponents`). See docs/analysis.md.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ssm_ms.forecasting.analysis_settings import TrueSystemSettings, ValidTimeSettings
from ssm_ms.nets.sensors import SensorLayout

FLOOR_FRAMES = 10  # images: the valid time counts errors above the reconstruction error on the last 10 given frames


def valid_time_split(
    settings: ValidTimeSettings, n_filter: int, n_predict: int | None, seq_len: int
) -> tuple[int, int]:
    """``(k, h)``: steps given and steps forecast for the valid time, the protocol's ``n_filter`` and ``n_predict``
    (else the rest of each sequence) where ``settings`` leave them unset."""
    k = settings.n_filter or n_filter
    return k, settings.horizon or n_predict or seq_len - k


class ValidTimeAccumulator:
    """Squared forecast errors per sequence and step, and the truth's statistics, over the test batches.

    The valid time needs the scale of the truth over the whole test set, known only at the end: errors are
    kept per step and thresholded in :meth:`steps`. Vectors: per component ``[B, h, D]``, each scaled by its
    std. Images: pooled, the mean squared error over the pixels ``[B, h, 1]`` scaled by the mean per-pixel
    variance, so that, as for vectors, a normalised error of 1 is as bad as predicting the mean frame (and
    background pixels that never change divide nothing).

    Images, in excess of the method's own floor: a decoder's reconstruction of frames it was given is already
    blurred (the full-size pendulum SSM: normalised error ~0.5 on the given frames), which would make every
    image forecast "invalid" from its first frame. So for images the error of a step is the part above the
    sequence's reconstruction error on its last :data:`FLOOR_FRAMES` given frames (the ``given`` pairs of
    :meth:`update`): ``sqrt(max(mse_t - mse_given, 0) / mean pixel variance)``. Valid while the forecast
    has lost no more than that to its reconstruction; a forecast that drifts off the object's phase soon
    exceeds it. Vectors keep the convention's plain error (no floor).

    Several sensors (``layout``, a :class:`~ssm_ms.nets.sensors.SensorLayout`): each stream is normalised as above on
    its own (an image pooled over its pixels, a vector per component), and a step's error is the root mean square of
    the streams' errors, each stream weighing the same whatever its size. Missing samples (NaN in the truth: a stream
    sampled at a lower rate) are left out; a step where a stream has none is judged on the others.
    """

    def __init__(self, layout: SensorLayout | None = None) -> None:
        self.errors: list[torch.Tensor] = []
        self.floors: list[torch.Tensor] = []
        self.total = self.total_sq = self.seen = None  # sums of the truth, and its samples, per component
        self.count = 0  # truth rows added (sequences x steps)
        self.clean = True
        self.pooled = False
        self.layout = layout
        self.streams = {} if layout is None else {s.name: ValidTimeAccumulator() for s in layout.streams}

    def add_forecast(
        self,
        filtered: torch.Tensor,
        predicted: torch.Tensor,
        truth: torch.Tensor,
        clean: bool,
        to_units: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ) -> None:
        """Add a batch of forecasts from the first ``k`` steps of sequences whose truth is ``truth [B, T, *obs_shape]``:
        the forecaster's estimate ``filtered [B, k, *obs_shape]`` of the given steps (the last :data:`FLOOR_FRAMES`
        of them are the floor) and its prediction ``predicted [B, h, *obs_shape]`` of the next ``h``; ``to_units``:
        applied to both and to the truth before the errors are taken (original units)."""
        if self.streams:
            if to_units is not None:
                filtered, predicted, truth = to_units(filtered), to_units(predicted), to_units(truth)
            self.clean = self.clean and clean
            parts = [self.layout.split(t) for t in (filtered, predicted, truth)]
            for name, acc in self.streams.items():
                acc.add_forecast(*(part[name] for part in parts), clean=clean)
            self.count += predicted.shape[0] * predicted.shape[1]
            return
        k, h = filtered.shape[1], predicted.shape[1]
        m = min(FLOOR_FRAMES, k)
        pred, given, future, truth_given = predicted, filtered[:, -m:], truth[:, k : k + h], truth[:, k - m : k]
        if to_units is not None:
            pred, future = to_units(pred), to_units(future)
            given, truth_given = to_units(given), to_units(truth_given)
        self.update(pred, future, clean=clean, given=(given, truth_given))

    def update(
        self,
        pred: torch.Tensor,
        truth: torch.Tensor,
        clean: bool = True,
        given: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> None:
        """Add a batch: predictions and truth ``[B, h, *obs_shape]``; ``clean``: the truth is noiseless;
        ``given``: the method's estimate of its last given measurements and their truth ``[B, m, *obs_shape]``
        (images: the floor; without it, none)."""
        self.clean = self.clean and clean
        pred, truth = pred.double(), truth.double()
        self.pooled = truth.dim() > 3
        sq = (pred - truth).pow(2)
        # a missing sample (NaN truth) is left out; a forecast that is not finite where the truth is, invalid
        sq = torch.where(truth.isnan(), torch.nan, sq.nan_to_num(nan=torch.inf))
        if self.pooled:  # images
            sq = sq.flatten(2).nanmean(2, keepdim=True)
            floor = torch.zeros(len(sq), dtype=torch.float64)
            if given is not None:
                floor = (given[0].double() - given[1].double()).pow(2).flatten(1).nanmean(1).nan_to_num().cpu()
            self.floors.append(floor)
        self.errors.append(sq.cpu())
        values = truth.flatten(2).reshape(-1, truth[0, 0].numel())
        seen = ~values.isnan()
        values = values.nan_to_num()
        total, total_sq, seen = values.sum(0).cpu(), values.pow(2).sum(0).cpu(), seen.sum(0).cpu()
        self.total = total if self.total is None else self.total + total
        self.total_sq = total_sq if self.total_sq is None else self.total_sq + total_sq
        self.seen = seen if self.seen is None else self.seen + seen
        self.count += len(values)

    def _variance(self) -> torch.Tensor:
        count = self.seen.clamp_min(1)
        mean = self.total / count
        var = (self.total_sq / count - mean.pow(2)).clamp_min(0)
        return (var.mean(0, keepdim=True) if self.pooled else var).clamp_min(1e-30)

    def normalised_errors(self) -> torch.Tensor:
        """``[N, h]``: each test sequence's normalised error at each forecast step (images: above its floor; several
        sensors: the root mean square over the streams). NaN where a step has no sample to judge it by."""
        if self.streams:
            per_stream = torch.stack([acc.normalised_errors() for acc in self.streams.values()])  # [S, N, h]
            return per_stream.pow(2).nanmean(0).sqrt()
        errors = torch.cat(self.errors)  # [N, h, D or 1]
        if self.pooled:
            errors = (errors - torch.cat(self.floors)[:, None, None]).clamp_min(0)
        return (errors / self._variance()).nanmean(-1).sqrt()

    def floor(self) -> float | None:
        """Images: the mean normalised reconstruction error on the given frames, ``sqrt(mse_given / var)`` (several
        sensors: the image streams' mean)."""
        if self.streams:
            floors = [f for f in (acc.floor() for acc in self.streams.values()) if f is not None]
            return sum(floors) / len(floors) if floors else None
        if not self.pooled:
            return None
        return float((torch.cat(self.floors) / self._variance()).sqrt().mean())

    def steps(self, threshold: float) -> tuple[torch.Tensor, int]:
        """Valid steps per test sequence ``[N]`` (``inf``: valid over the whole horizon) and the horizon."""
        from ssm_ms.analysis import valid_steps

        errors = self.normalised_errors()
        return valid_steps(errors, threshold), errors.shape[1]

    def growth(self) -> dict[str, float]:
        """The mean normalised error at the first, a quarter, half and last forecast step: how errors grow.

        Over the sequences whose forecast stayed finite at every step: a diverged one is left out, as the scores
        leave it out (NaN where none stayed finite)."""
        errors = self.normalised_errors()
        curve = errors[torch.isfinite(errors).all(1)].mean(0)
        h = len(curve)
        return {str(step): float(curve[step - 1]) for step in sorted({1, max(1, h // 4), max(1, h // 2), h})}

    def report(self, threshold: float, n_filter: int, dt: float | None, largest: float | None) -> dict[str, Any]:
        """The results file's ``valid_time``: :func:`ssm_ms.analysis.summarize_valid_time` of the valid steps at
        ``threshold`` (in seconds with ``dt``, and in Lyapunov times with the true system's ``largest`` exponent;
        without ``dt``, in steps only), with the settings, the error growth and (images) the floor."""
        from ssm_ms.analysis import summarize_valid_time

        steps, horizon = self.steps(threshold)
        vt = summarize_valid_time(steps, horizon, dt or 1.0, largest)
        if dt is None:
            vt = {k: v for k, v in vt.items() if "seconds" not in k and "lyapunov" not in k}
        vt.update(
            threshold=threshold,
            n_filter=n_filter,
            truth="noiseless" if self.clean else "noisy",
            dt=dt,
            error_at_step=self.growth(),
            given_error=self.floor(),
        )
        return vt


def reference_exponents(dm: Any, settings: TrueSystemSettings | None = None) -> dict[str, Any] | None:
    """The true system's Lyapunov exponents per time unit, where the data set can give them: computed from
    its own equations (``true_transition``, from the first states of the test sequences; ``settings``: a
    :class:`~ssm_ms.forecasting.analysis_settings.TrueSystemSettings` or a mapping of its options, default its
    defaults) and cached in the data set's cache folder, or stated (``known_largest_exponent``, e.g. 0 for the
    undamped simple pendulum)."""
    if dm is None:
        return None
    if callable(getattr(dm, "true_transition", None)) and getattr(dm, "sample_period", None):
        from ssm_ms.analysis import lyapunov_spectrum

        settings = TrueSystemSettings() if settings is None else TrueSystemSettings.of(settings)
        options = settings.as_dict()
        name = "true_exponents_" + "_".join(f"{k}{v}" for k, v in sorted(options.items())) + ".json"
        cache = Path(dm.cache_dir) / name if hasattr(dm, "cache_dir") else None
        if cache is not None and cache.is_file():
            try:
                return json.loads(cache.read_text())
            except ValueError:  # cut short (a run stopped while it wrote it): computed again below
                pass
        test = dm.datasets.get("test") if hasattr(dm, "datasets") else None
        states = getattr(test, "arrays", {}).get("state") if test is not None else None
        if states is None:
            return None
        x0 = torch.from_numpy(np.array(states[: settings.runs, 0], dtype=np.float64))
        res = lyapunov_spectrum(
            dm.true_transition(),
            x0,
            steps=settings.lyapunov_steps,
            dt=float(dm.sample_period),
            transient=settings.transient,
            align=settings.align,
        )
        result = {
            "exponents": res.exponents.tolist(),
            "largest": float(res.exponents[0]),
            "source": f"the data set's equations, Benettin QR over {len(x0)} runs of {settings.lyapunov_steps} steps",
        }
        if cache is not None:
            cache.write_text(json.dumps(result))
        return result
    if getattr(dm, "known_largest_exponent", None) is not None:
        return {"largest": float(dm.known_largest_exponent), "source": "known for this system"}
    return None
