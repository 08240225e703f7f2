"""Batched unscented Kalman filter (additive noise) over a learned SSM ``x[t+1] = f(x[t])``, ``y[t] = g(x[t])``, or
``x[t+1] = f(x[t], u[t])`` for a system driven by known inputs (``filter(..., u=...)``, ``predict(..., u=...)``).

The filter infers the states of unseen trajectories from their measurements with the learned ``f`` and
``g`` and nothing else (no training). It is vectorised over trajectories and sigma points: each step
calls ``g`` once and ``f`` once on ``[B * (2d+1), d]`` (``2d`` when the central point has zero weight,
e.g. ``beta=0``); a linear ``g`` is not called at all (its matrix gives the update exactly). Time goes
mostly into ``f`` (see benchmarks/results/ukf.md), which may run under ``torch.autocast``. The filter runs
on the device and dtype of ``y`` and is differentiable (gradients reach ``f``, ``g``, ``y``, ``x0``, ``P0``).

Convention::

    prior N(x0, P0) for time 0
    for t in 0..T-1:  update with y[t]  -> posterior (means[:, t], covs[:, t])
                      predict through f -> prior for t+1   (skipped after the last step)

The one-step prior for time T (the first forecast with its covariance) is
``ukf.predict(means[:, -1], covs[:, -1])``; a point forecast iterates ``f`` from ``means[:, -1]``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import NamedTuple, Union

import torch
from torch import Tensor

from ssm_ms.inference.shared import call_model, check_autocast, check_inputs, check_measurements, driven

# Plain types only, so that configs (jsonargparse / LightningCLI) can give them; tensors work too at run time.
Variance = Union[float, list[float], list[list[float]]]  # noqa: UP007 (a run-time alias configs are checked against)


class CovarianceJitterWarning(UserWarning):
    """A covariance was not numerically positive definite and got jitter on its diagonal."""


class UKFResult(NamedTuple):
    """Filtered (posterior) estimates: ``means [B, T, d]``, ``covs [B, T, d, d]``."""

    means: Tensor
    covs: Tensor


def _check_variance(value: Variance, name: str, allow_zero: bool) -> Tensor:
    """Validate a variance given as scalar, per-dimension vector or full matrix; return it as float64."""
    try:
        t = torch.as_tensor(value, dtype=torch.float64).detach().cpu()
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a number, a list of numbers or a square matrix, got {value!r}") from err
    what = "non-negative" if allow_zero else "positive"
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, got {value!r}")
    if t.ndim in (0, 1):
        bad = (t < 0) if allow_zero else (t <= 0)
        if t.numel() == 0 or bad.any():
            raise ValueError(f"{name} must be {what} (a variance, not a std), got {t.tolist()}")
    elif t.ndim == 2:
        if t.shape[0] != t.shape[1]:
            raise ValueError(f"{name} as a matrix must be square, got shape {list(t.shape)}")
        if not torch.allclose(t, t.T, rtol=1e-6, atol=1e-12):
            raise ValueError(f"{name} must be a symmetric matrix; symmetrise it, e.g. (A + A.T) / 2")
        eig_min = torch.linalg.eigvalsh(t).min().item()
        tol = 1e-12 * max(1.0, t.abs().max().item())
        if eig_min < -tol or (not allow_zero and eig_min <= tol):
            raise ValueError(
                f"{name} must be positive {'semi-' if allow_zero else ''}definite, its smallest eigenvalue is "
                f"{eig_min:.3g}: use a scalar or per-dimension variance, or add a multiple of the identity"
            )
    else:
        raise ValueError(f"{name} must be a scalar, a vector or a matrix, got {t.ndim} dimensions")
    return t


def _variance_dim(t: Tensor) -> int | None:
    return None if t.ndim == 0 else t.shape[0]


def _as_matrix(t: Tensor, dim: int, name: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Scalar / vector / matrix variance -> ``[dim, dim]`` matrix on ``device``."""
    if t.ndim >= 1 and t.shape[0] != dim:
        raise ValueError(f"{name} has {t.shape[0]} entries per side but the dimension is {dim}")
    t = t.to(dtype=dtype, device=device)
    if t.ndim == 0:
        return t * torch.eye(dim, dtype=dtype, device=device)
    if t.ndim == 1:
        return torch.diag(t)
    return t


class _Setup:
    """Per-call constants of the filter (weights, sigma-point pattern, noise matrices)."""

    def __init__(self, d: int, wm: Tensor, wc: Tensor, pattern: Tensor, q: Tensor, mode: str):
        self.d, self.wm, self.wc, self.pattern, self.q, self.mode = d, wm, wc, pattern, q, mode
        self.pattern_t = pattern.t().contiguous()  # [d, n]
        # weighted mean over sigma points as one matrix product: [B, n*d] @ kron(wm, I_d) -> [B, d]
        self.wm_kron = torch.kron(wm.unsqueeze(-1), torch.eye(d, dtype=wm.dtype, device=wm.device))
        self.wm_col = wm.unsqueeze(-1)  # [n, 1]
        self.sqrt_wc: Tensor = wc
        self.eye_n: Tensor = wc
        self.r: Tensor | None = None
        self.r_std: Tensor | None = None
        self.u_scale: Tensor | None = None
        self.r_chol: Tensor | None = None
        self.h: Tensor | None = None  # g(x) = h x + c when g is linear (dense mode)
        self.c: Tensor | None = None


class UnscentedKalmanFilter:
    """Batched unscented Kalman filter with additive Gaussian process and measurement noise.

    Args:
        f: transition, ``[N, d] -> [N, d]`` (any callable / ``nn.Module``).
        g: observation model, ``[N, d] -> [N, *obs_shape]``.
        process_var: variance ``Q`` of the additive process noise: scalar, per-dimension list or
            ``d x d`` matrix (positive semi-definite; 0 means a deterministic ``f``).
        measurement_var: variance ``R`` of the measurement noise: scalar, per-component list over the
            flattened observation, or matrix (positive definite).
        init_var: default prior covariance ``P0`` at time 0 when ``filter`` gets none.
        alpha, beta, kappa: unscented transform; ``lambda = alpha^2 (d + kappa) - d``, sigma points
            ``m +- sqrt(d + lambda) * columns of chol(P)``. The defaults (1, 2, 0) give non-negative
            weights, so every covariance is a sum of outer products (PSD by construction) and float32
            is safe; a small alpha (e.g. 1e-3) gives a large negative central weight. With
            ``(1, 0, 0)`` (the cubature rule) the central point has zero weight and is not evaluated:
            ``2d`` calls of ``f`` per trajectory instead of ``2d+1``.
        jitter: first diagonal jitter, relative to the mean diagonal (and at least the dtype's eps),
            tried when a Cholesky fails; it is multiplied by 10 up to ``max_jitter_tries`` times, and only
            the failing trajectories get it.
        max_jitter_tries: attempts before falling back to the diagonal (with a warning).
        state_dim: ``d``; if omitted, taken from ``f.state_dim``, a non-scalar variance, or ``x0``.
        innovation: ``"dense"``: Cholesky of the innovation covariance ``S`` (``p x p``, ``p`` the
            flattened observation size), cost ``O(p^3)`` per trajectory and step: about 64 MFLOP for a
            24x24 image. ``"low_rank"``: the same update written in the ``2d+1`` sigma-point space
            (``S = R + U U^T`` with ``U`` of rank ``2d+1``, Woodbury), cost ``O(p (2d+1)^2 + p^2 (2d+1))``
            with a full ``R`` and ``O(p (2d+1)^2)`` with a diagonal one; needs non-negative weights.
            ``"auto"`` (default) picks ``low_rank`` when the weights allow it and ``p > 2d+1``.
            In ``dense`` mode a linear ``g`` (``nn.Linear``, or a module with ``observation_matrix(d)``
            such as :class:`~ssm_ms.nets.readout.Projection`) is not evaluated on sigma points: the
            unscented transform of a linear map is exact, so the update uses ``H P H^T`` and ``P H^T``
            directly (the same result, fewer operations). Wrap ``g`` in a function to force sigma points.
        iterations: measurement updates per step (default 1: the UKF's own). With ``k > 1`` the update is the
            iterated posterior linearisation (García-Fernández, Svensson, Morelande & Särkkä, "Posterior
            Linearization Filter", IEEE TSP 2015): ``g`` is linearised statistically over the sigma points of the
            latest posterior instead of the prior's, and the prior is updated again with that line (the part of
            ``g`` the line does not explain added to ``R``), ``k - 1`` more times. An informative measurement of
            a sharp ``g`` (a camera's frame: many pixels, each a steep function of the state) moves the
            posterior far inside the prior's spread, where the prior's linearisation no longer holds; iterating
            follows it there. Costs ``k`` calls of ``g`` per step; with ``innovation="low_rank"`` only.
        autocast: ``None`` (default: the dtype of ``y``), ``"bfloat16"`` or ``"float16"``: evaluate ``f``
            and ``g`` under ``torch.autocast`` with this dtype, so their matrix products run in reduced
            precision (``f`` is most of a step's time, see benchmarks/results/ukf.md); means,
            covariances and Cholesky factors stay in ``y``'s dtype.

    The paper's settings for Lorenz in normalised units are the defaults: ``P0 = 0.1 I``,
    measurement variance 0.5, process variance 1e-6.
    """

    def __init__(
        self,
        f: Callable[[Tensor], Tensor],
        g: Callable[[Tensor], Tensor],
        process_var: Variance = 1e-6,
        measurement_var: Variance = 0.5,
        init_var: Variance = 0.1,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        jitter: float = 1e-9,
        max_jitter_tries: int = 6,
        state_dim: int | None = None,
        innovation: str = "auto",
        iterations: int = 1,
        autocast: str | None = None,
    ):
        self.f, self.g = f, g
        whole = (
            isinstance(iterations, (int, float)) and not isinstance(iterations, bool) and float(iterations).is_integer()
        )
        if not whole or iterations < 1:
            raise ValueError(f"iterations must be a whole number >= 1 (1: the UKF's own update), got {iterations!r}")
        self.iterations = int(iterations)
        self.autocast = check_autocast(autocast)
        self.process_var = _check_variance(process_var, "process_var", allow_zero=True)
        self.measurement_var = _check_variance(measurement_var, "measurement_var", allow_zero=False)
        self.init_var = _check_variance(init_var, "init_var", allow_zero=False)
        if alpha <= 0:
            raise ValueError(f"alpha must be > 0, got {alpha}")
        if jitter <= 0 or max_jitter_tries < 1:
            raise ValueError(f"jitter must be > 0 and max_jitter_tries >= 1, got {jitter}, {max_jitter_tries}")
        if innovation not in ("auto", "dense", "low_rank"):
            raise ValueError(f"innovation must be 'auto', 'dense' or 'low_rank', got {innovation!r}")
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)
        self.jitter, self.max_jitter_tries = float(jitter), int(max_jitter_tries)
        self.innovation = innovation
        dims = {n: _variance_dim(v) for n, v in (("process_var", self.process_var), ("init_var", self.init_var))}
        dims = {n: v for n, v in dims.items() if v is not None}
        if state_dim is None:
            from_f = getattr(f, "state_dim", None)
            state_dim = from_f if isinstance(from_f, int) else next(iter(dims.values()), None)
        if state_dim is not None:
            if not isinstance(state_dim, int) or state_dim < 1:
                raise ValueError(f"state_dim must be a positive int, got {state_dim!r}")
            for n, v in dims.items():
                if v != state_dim:
                    raise ValueError(f"{n} has {v} entries per side but state_dim is {state_dim}")
        self.state_dim: int | None = state_dim
        self._events: list[tuple[int, str, float, int]] = []

    # ----------------------------------------------------------------------------------------------
    # unscented transform pieces
    def weights(self, d: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, float]:
        """Mean weights ``[2d+1]``, covariance weights ``[2d+1]`` and the sigma-point scale ``sqrt(d+lambda)``."""
        lam = self.alpha**2 * (d + self.kappa) - d
        if d + lam <= 0:
            raise ValueError(f"alpha^2 (d + kappa) = {d + lam:.3g} must be > 0 (d = {d}): raise alpha or kappa")
        wm = torch.full((2 * d + 1,), 0.5 / (d + lam), dtype=torch.float64)
        wc = wm.clone()
        wm[0] = lam / (d + lam)
        wc[0] = lam / (d + lam) + 1.0 - self.alpha**2 + self.beta
        return wm.to(dtype=dtype, device=device), wc.to(dtype=dtype, device=device), math.sqrt(d + lam)

    def _setup(self, d: int, p: int | None, dtype: torch.dtype, device: torch.device) -> _Setup:
        """Everything a step needs that does not change over time, built once per call (p=None: predict only)."""
        wm, wc, scale = self.weights(d, dtype, device)
        eye = torch.eye(d, dtype=dtype, device=device)
        pattern = scale * torch.cat([torch.zeros(1, d, dtype=dtype, device=device), eye, -eye])  # [n, d]
        if float(wm[0]) == 0.0 and float(wc[0]) == 0.0:  # e.g. beta=0 (cubature rule): the centre is unused
            wm, wc, pattern = wm[1:], wc[1:], pattern[1:]
        q = _as_matrix(self.process_var, d, "process_var", dtype, device)
        if p is None:
            return _Setup(d=d, wm=wm, wc=wc, pattern=pattern, q=q, mode="none")
        if p < 1:
            raise ValueError("measurements must have at least one component")
        r = self.measurement_var
        if r.ndim >= 1 and r.shape[0] != p:
            raise ValueError(
                f"measurement_var has {r.shape[0]} entries per side but a measurement has {p} components "
                "(flattened): give a scalar or one variance per component"
            )
        nonneg = bool((wc >= 0).all())
        mode = self.innovation
        if mode == "auto":
            mode = "low_rank" if nonneg and p > len(wc) else "dense"
        if self.iterations > 1 and mode != "low_rank":
            raise ValueError(
                f"iterations > 1 needs innovation='low_rank' (measurements larger than the 2d+1 sigma points, "
                f"non-negative weights), here {mode!r} with {p} components: use iterations: 1"
            )
        if mode == "low_rank" and not nonneg:
            raise ValueError(
                "innovation='low_rank' needs non-negative covariance weights: use alpha=1 and kappa>=0, or "
                "innovation='dense'"
            )
        setup = _Setup(d=d, wm=wm, wc=wc, pattern=pattern, q=q, mode=mode)
        sqrt_wc = wc.clamp_min(0).sqrt()
        setup.sqrt_wc = sqrt_wc.unsqueeze(-1)
        if mode == "dense":
            setup.r = _as_matrix(r, p, "measurement_var", dtype, device)
            setup.h, setup.c = self._linear_observation(d, p, dtype, device)
        elif r.ndim <= 1:  # diagonal R: whitening is a division by the std
            r_std = r.to(dtype=dtype, device=device).sqrt().expand(p)
            setup.r_std = r_std
            setup.u_scale = sqrt_wc.unsqueeze(-1) / r_std  # [n, p]
        else:
            setup.r_chol = torch.linalg.cholesky(r.to(dtype=dtype, device=device))
        setup.eye_n = torch.eye(len(wc), dtype=dtype, device=device)
        return setup

    def _linear_observation(
        self, d: int, p: int, dtype: torch.dtype, device: torch.device
    ) -> tuple[Tensor | None, Tensor | None]:
        """``(H [p, d], c [p] or None)`` when ``g(x) = H x + c`` is known to be linear, else ``(None, None)``."""
        g = self.g
        if isinstance(g, torch.nn.Linear):
            h, c = g.weight, g.bias
        elif callable(getattr(g, "observation_matrix", None)):
            h, c = g.observation_matrix(d), None
        else:
            return None, None
        if tuple(h.shape) != (p, d):
            raise ValueError(
                f"g is linear with a {list(h.shape)} matrix but states have {d} components and measurements {p}"
            )
        return h.to(dtype=dtype, device=device), None if c is None else c.to(dtype=dtype, device=device)

    def _cholesky(self, a: Tensor, what: str, step: int) -> Tensor:
        """Lower Cholesky factor of the batch ``a [B, n, n]`` (lower triangle read), jitter on failing members."""
        chol, info = torch.linalg.cholesky_ex(a)
        if not bool(info.any()):
            return chol
        fail = info != 0
        a = 0.5 * (a + a.transpose(-1, -2))
        n = a.shape[-1]
        eye = torch.eye(n, dtype=a.dtype, device=a.device)
        diag = a.diagonal(dim1=-2, dim2=-1)
        scale = diag.detach().abs().mean(-1).clamp_min(torch.finfo(a.dtype).tiny)
        level = torch.zeros_like(scale)  # jitter per trajectory, relative to its mean diagonal
        jit = max(self.jitter, float(torch.finfo(a.dtype).eps))  # below eps a jitter changes nothing
        for _ in range(self.max_jitter_tries):
            level = torch.where(fail, torch.full_like(level, jit), level)
            chol, info = torch.linalg.cholesky_ex(a + (level * scale)[:, None, None] * eye)
            fail = info != 0
            if not bool(fail.any()):
                self._events.append((step, what, float(level.max()), int((level > 0).sum())))
                return chol
            jit *= 10.0
        warnings.warn(
            f"UKF step {step}: the {what} covariance of {int(fail.sum())} trajectories is not positive "
            f"definite even with jitter {float(level.max()):.1e} x mean diagonal; using its diagonal for them. "
            "Check f and g for NaN/inf or exploding states, or raise process_var / measurement_var.",
            CovarianceJitterWarning,
            stacklevel=3,
        )
        fallback = torch.diag_embed(diag.clamp_min(torch.finfo(a.dtype).tiny))
        a_fix = torch.where(fail[:, None, None], fallback, a + (level * scale)[:, None, None] * eye)
        return torch.linalg.cholesky_ex(a_fix)[0]

    def _sigma_points(self, mean: Tensor, cov: Tensor, setup: _Setup, what: str, step: int) -> tuple[Tensor, Tensor]:
        """Sigma points ``[B, 2d+1, d]`` (mean, then mean +- scale * columns of chol(cov)) and their offsets."""
        return self._spread(mean, self._cholesky(cov, what, step), setup)

    @staticmethod
    def _spread(mean: Tensor, chol: Tensor, setup: _Setup) -> tuple[Tensor, Tensor]:
        """The sigma points and offsets of ``N(mean, chol chol^T)`` (``chol [B, d, d]`` lower, contiguous)."""
        b, d = mean.shape
        # offsets[b] = pattern @ chol[b]^T, as one [B*d, d] @ [d, n] product
        offsets = (chol.reshape(b * d, d) @ setup.pattern_t).view(b, d, -1).transpose(-1, -2)
        return mean.unsqueeze(-2) + offsets, offsets

    # ----------------------------------------------------------------------------------------------
    def predict(self, mean: Tensor, cov: Tensor, u: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """One prediction through ``f``: posterior ``(mean [B, d], cov [B, d, d])`` at t -> prior at t+1 (under the
        inputs ``u [B, m]`` applied from t to t+1, for a driven ``f``)."""
        setup = self._setup(mean.shape[-1], None, mean.dtype, mean.device)
        self._events = []
        mean, cov = self._predict(mean, cov, setup, -1, u)
        self._warn_jitter()
        return mean, 0.5 * (cov + cov.transpose(-1, -2))

    def _predict(
        self, mean: Tensor, cov: Tensor, setup: _Setup, step: int, u: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        b, d = mean.shape
        sigma, _ = self._sigma_points(mean, cov, setup, "posterior", step)
        fx = call_model(driven(self.f, u, sigma.shape[1]), sigma.reshape(-1, d), self.autocast)
        mean_pred = fx.reshape(b, -1) @ setup.wm_kron
        dev = fx.reshape(b, -1, d) - mean_pred.unsqueeze(-2)
        return mean_pred, torch.baddbmm(setup.q, dev.transpose(-1, -2) * setup.wc, dev)

    def update(self, mean: Tensor, cov: Tensor, y_t: Tensor) -> tuple[Tensor, Tensor]:
        """One measurement update: prior ``(mean [B, d], cov [B, d, d])`` and ``y_t [B, *obs_shape]`` -> posterior."""
        y_flat = y_t.reshape(y_t.shape[0], -1)
        setup = self._setup(mean.shape[-1], y_flat.shape[-1], mean.dtype, mean.device)
        self._events = []
        mean, cov = self._update(mean, cov, y_flat, setup, -1)
        self._warn_jitter()
        return mean, 0.5 * (cov + cov.transpose(-1, -2))

    def _update(self, mean: Tensor, cov: Tensor, y_flat: Tensor, setup: _Setup, step: int) -> tuple[Tensor, Tensor]:
        post_mean, post_cov = self._ukf_update(mean, cov, y_flat, setup, step)
        if self.iterations > 1:
            prior_chol = self._cholesky(cov, "prior", step)
            for _ in range(self.iterations - 1):
                post_mean, post_cov = self._relinearised_update(
                    mean, prior_chol, post_mean, post_cov, y_flat, setup, step
                )
        return post_mean, post_cov

    def _whiten(self, v: Tensor, setup: _Setup) -> Tensor:
        """``R^-1/2 v`` for ``v [B, p, k]`` (``low_rank`` mode's diagonal or Cholesky-factored ``R``)."""
        if setup.r_chol is None:
            return v / setup.r_std.unsqueeze(-1)
        return torch.linalg.solve_triangular(setup.r_chol, v, upper=False)

    def _relinearised_update(
        self,
        prior_mean: Tensor,
        prior_chol: Tensor,
        mean: Tensor,
        cov: Tensor,
        y_flat: Tensor,
        setup: _Setup,
        step: int,
    ) -> tuple[Tensor, Tensor]:
        """The prior ``N(prior_mean, L L^T)`` (``L = prior_chol``) updated with ``g`` linearised over the sigma points
        of ``N(mean, cov)``: ``g(x) ~ H x + c + e``, ``e ~ N(0, Omega)`` (statistical linear regression), then the
        Kalman update under ``y = H x + c + e + v``, ``v ~ N(0, R)``, written in the state space::

            B = (H L)^T (Omega + R)^-1 (H L),   b = (H L)^T (Omega + R)^-1 (y - H prior_mean - c)
            mean+ = prior_mean + L (I + B)^-1 b,   cov+ = L (I + B)^-1 L^T   (PSD by construction)

        ``Omega = Y_r^T Y_r`` (``Y_r``: the sigma points' images less the line's, weighted) has rank ``<= 2d+1``, so
        ``(Omega + R)^-1`` is a Woodbury product; nothing ``p x p`` is formed. At ``N(mean, cov)`` equal to the prior
        this is the UKF's own update."""
        b, d = mean.shape
        chol = self._cholesky(cov, "iterated posterior", step)  # also the sigma points' weighted covariance's
        sigma, x_dev = self._spread(mean, chol, setup)
        gy = call_model(self.g, sigma.reshape(-1, d), self.autocast).reshape(b, sigma.shape[1], -1)
        y_pred = (gy * setup.wm_col).sum(-2)
        xs, ys = x_dev * setup.sqrt_wc, (gy - y_pred.unsqueeze(-2)) * setup.sqrt_wc  # [B, n, d], [B, n, p]
        # H^T = P^-1 X_s^T Y_s [B, d, p]; the residual Y_r = Y_s - X_s H^T [B, n, p]
        h_t = torch.cholesky_solve(xs.transpose(-1, -2) @ ys, chol)
        resid = ys - xs @ h_t
        innov = y_flat - y_pred - ((prior_mean - mean).unsqueeze(-2) @ h_t).squeeze(-2)  # y - H prior_mean - c
        observed = torch.isfinite(y_flat)
        if not bool(observed.all()):  # components a sensor did not take: no information
            h_t, resid = h_t * observed.unsqueeze(-2), resid * observed.unsqueeze(-2)
            innov = torch.where(observed, innov, torch.zeros_like(innov))
        hl_w = self._whiten((h_t.transpose(-1, -2) @ prior_chol), setup)  # R^-1/2 H L [B, p, d]
        v_w = self._whiten(resid.transpose(-1, -2), setup)  # R^-1/2 Y_r^T [B, p, n]
        e_w = self._whiten(innov.unsqueeze(-1), setup)  # [B, p, 1]
        # (Omega + R)^-1 in whitened coordinates: I - V (I + V^T V)^-1 V^T
        chol_a = self._cholesky(torch.baddbmm(setup.eye_n, v_w.transpose(-1, -2), v_w), "residual", step)
        vt = v_w.transpose(-1, -2)
        m, ve = torch.cholesky_solve(vt @ hl_w, chol_a), torch.cholesky_solve(vt @ e_w, chol_a)
        hl_t = hl_w.transpose(-1, -2)
        big_b = hl_t @ hl_w - (vt @ hl_w).transpose(-1, -2) @ m
        small_b = hl_t @ e_w - (vt @ hl_w).transpose(-1, -2) @ ve
        eye_d = torch.eye(d, dtype=mean.dtype, device=mean.device)
        chol_k = self._cholesky(eye_d + 0.5 * (big_b + big_b.transpose(-1, -2)), "iterated information", step)
        z = torch.linalg.solve_triangular(chol_k, torch.cat([prior_chol.transpose(-1, -2), small_b], -1), upper=False)
        z_l, z_b = z[..., :d], z[..., d:]  # K^-1 = (chol_k chol_k^T)^-1: L K^-1 L^T = (z_l)^T z_l
        return prior_mean + (z_l.transpose(-1, -2) @ z_b).squeeze(-1), z_l.transpose(-1, -2) @ z_l

    def _ukf_update(self, mean: Tensor, cov: Tensor, y_flat: Tensor, setup: _Setup, step: int) -> tuple[Tensor, Tensor]:
        b, d = mean.shape
        p = y_flat.shape[-1]
        if setup.h is not None:  # linear g: the moments the unscented transform would give, exactly
            ct = setup.h @ cov  # C^T = H P, [B, p, d]
            y_pred = mean @ setup.h.t() if setup.c is None else torch.addmm(setup.c, mean, setup.h.t())
            s = ct @ setup.h.t() + setup.r
            return self._dense_correction(mean, cov, ct, s, (y_flat - y_pred).unsqueeze(-1), step)
        sigma, x_dev = self._sigma_points(mean, cov, setup, "prior", step)
        gy = call_model(self.g, sigma.reshape(-1, d), self.autocast).reshape(b, sigma.shape[1], p)
        y_pred = (gy * setup.wm_col).sum(-2)
        y_dev = gy - y_pred.unsqueeze(-2)  # [B, n, p]
        observed = torch.isfinite(y_flat)
        if not bool(observed.all()):  # samples a sensor did not take (NaN): no information, as an infinite variance
            y_dev = y_dev * observed.unsqueeze(-2)
            y_flat = torch.where(observed, y_flat, y_pred)
        innov = (y_flat - y_pred).unsqueeze(-1)  # [B, p, 1]
        if setup.mode == "dense":
            # One product gives C^T and S: [x_dev, y_dev]^T Wc [x_dev, y_dev].
            z = torch.cat([x_dev, y_dev], dim=-1)
            m = (z.transpose(-1, -2) * setup.wc) @ z
            return self._dense_correction(mean, cov, m[:, d:, :d], m[:, d:, d:] + setup.r, innov, step)
        # S = R + U U^T with U = Y_dev^T sqrt(Wc); C = X_s^T U^T with X_s = sqrt(Wc) X_dev. With
        # G = U^T R^-1 U and A = I + G (Woodbury): C S^-1 e = X_s^T A^-1 U^T R^-1 e and
        # P+ = P - C S^-1 C^T = X_s^T A^-1 X_s (PSD by construction).
        if setup.r_chol is None:
            u_w, e_w = y_dev * setup.u_scale, innov / setup.r_std.unsqueeze(-1)
        else:
            u_w = torch.linalg.solve_triangular(
                setup.r_chol, (y_dev * setup.sqrt_wc).transpose(-1, -2), upper=False
            ).transpose(-1, -2)
            e_w = torch.linalg.solve_triangular(setup.r_chol, innov, upper=False)
        a = torch.baddbmm(setup.eye_n, u_w, u_w.transpose(-1, -2))
        chol_a = self._cholesky(a, "innovation (sigma-point space)", step)
        rhs = torch.cat([x_dev * setup.sqrt_wc, u_w @ e_w], dim=-1)  # [B, n, d+1]
        z = torch.linalg.solve_triangular(chol_a, rhs, upper=False)
        z_x, z_e = z[..., :d], z[..., d:]
        z_xt = z_x.transpose(-1, -2)
        return mean + (z_xt @ z_e).squeeze(-1), z_xt @ z_x

    def _dense_correction(
        self, mean: Tensor, cov: Tensor, ct: Tensor, s: Tensor, innov: Tensor, step: int
    ) -> tuple[Tensor, Tensor]:
        """Posterior from ``C^T = P_xy^T [B, p, d]``, ``S = P_yy + R [B, p, p]`` and the innovation ``[B, p, 1]``.

        ``W = L_S^-1 [C^T, innov]``: ``m+ = m + W_C^T W_e``, ``P+ = P - W_C^T W_C`` (no inverse of ``S``).
        """
        d, p = mean.shape[-1], s.shape[-1]
        rhs = torch.cat([ct, innov], dim=-1)  # [B, p, d+1]
        if p == 1 and bool((s > 0).all()):  # scalar measurement: L_S = sqrt(S)
            w = rhs * s.rsqrt()
        else:
            w = torch.linalg.solve_triangular(self._cholesky(s, "innovation", step), rhs, upper=False)
        w_c, w_e = w[..., :d], w[..., d:]
        w_ct = w_c.transpose(-1, -2)
        return mean + (w_c * w_e).sum(-2), cov - (w_ct * w_c if p == 1 else w_ct @ w_c)

    # ----------------------------------------------------------------------------------------------
    def filter(
        self, y: Tensor, x0: Tensor | None = None, P0: Tensor | None = None, u: Tensor | None = None
    ) -> UKFResult:
        """Filtered means ``[B, T, d]`` and covariances ``[B, T, d, d]`` of ``y [B, T, *obs_shape]`` (with the inputs
        ``u [B, >= T - 1, m]`` of a driven ``f``: ``u[:, t]`` moves the state from t to t+1).

        ``x0``: prior mean at time 0, ``[d]`` or ``[B, d]`` (default zeros). ``P0``: prior covariance,
        ``[d, d]`` or ``[B, d, d]`` (default ``init_var``), symmetric positive definite.
        """
        bsz, steps = check_measurements(y)
        check_inputs(u, bsz, steps - 1, "UKF")
        dtype, device = y.dtype, y.device
        d = self._resolve_state_dim(x0, P0)
        mean = self._initial_mean(x0, bsz, d, dtype, device)
        cov = self._initial_cov(P0, bsz, d, dtype, device)

        # Check g against y once, on the initial mean.
        try:
            probe = call_model(self.g, mean[:1], self.autocast)
        except RuntimeError as err:
            raise ValueError(
                f"g failed on a state of dimension {d} ({err}): does state_dim match the SSM's g?"
            ) from err
        if not isinstance(probe, Tensor) or probe.ndim < 1 or probe.shape[0] != 1:
            raise ValueError("g must map [N, d] states to a tensor [N, *obs_shape]")
        if tuple(probe.shape[1:]) != tuple(y.shape[2:]):
            raise ValueError(
                f"g maps a state to observations of shape {list(probe.shape[1:])} but y has measurements of "
                f"shape {list(y.shape[2:])} (y is {list(y.shape)} = [B, T, *obs_shape]): make g match the data"
            )
        y_flat = y.reshape(bsz, steps, -1)
        setup = self._setup(d, y_flat.shape[-1], dtype, device)

        self._events = []
        means, covs = [], []
        for t in range(steps):
            mean, cov = self._update(mean, cov, y_flat[:, t], setup, t)
            means.append(mean)
            covs.append(cov)
            if t + 1 < steps:
                mean, cov = self._predict(mean, cov, setup, t, None if u is None else u[:, t])
        self._warn_jitter()
        covs_t = torch.stack(covs, dim=1)
        # The recursion reads only lower triangles (Cholesky); symmetrise the outputs once.
        return UKFResult(torch.stack(means, dim=1), 0.5 * (covs_t + covs_t.transpose(-1, -2)))

    # ----------------------------------------------------------------------------------------------
    def _warn_jitter(self) -> None:
        """One summary warning for the jitter added since the events were last cleared."""
        if self._events:
            first = self._events[0]
            worst = max(e[2] for e in self._events)
            warnings.warn(
                f"UKF: jitter was added to non-positive-definite covariances at {len(self._events)} Cholesky "
                f"factorisations, first at step {first[0]} ({first[1]}, {first[3]} trajectories), largest "
                f"jitter {worst:.1e} x mean diagonal. A near-singular covariance usually means too little "
                "process noise for f (raise process_var) or float32 round-off.",
                CovarianceJitterWarning,
                stacklevel=3,
            )
        self._events = []

    def initial_covariance(self, batch: int, d: int, dtype: torch.dtype, device: torch.device | None = None) -> Tensor:
        """The default prior covariance ``[batch, d, d]`` (``init_var``), for a filter run step by step."""
        return self._initial_cov(None, batch, d, dtype, device or torch.device("cpu"))

    def _resolve_state_dim(self, x0: Tensor | None, P0: Tensor | None) -> int:
        cands = []
        if x0 is not None:
            cands.append(("x0", torch.as_tensor(x0).shape[-1] if torch.as_tensor(x0).ndim else None))
        if P0 is not None:
            cands.append(("P0", torch.as_tensor(P0).shape[-1] if torch.as_tensor(P0).ndim else None))
        d = self.state_dim
        for name, v in cands:
            if v is None:
                raise ValueError(f"{name} must be a tensor with a state dimension, got a scalar")
            if d is None:
                d = v
            elif v != d:
                raise ValueError(f"{name} has state dimension {v} but the filter's state_dim is {d}")
        if d is None:
            raise ValueError(
                "the state dimension is unknown: pass state_dim=..., an f with a state_dim attribute, or x0"
            )
        return d

    @staticmethod
    def _initial_mean(x0, bsz, d, dtype, device) -> Tensor:
        if x0 is None:
            return torch.zeros(bsz, d, dtype=dtype, device=device)
        x0 = torch.as_tensor(x0).to(dtype=dtype, device=device)
        if x0.ndim == 1:
            return x0.expand(bsz, d)
        if x0.ndim == 2 and x0.shape[0] == bsz:
            return x0
        raise ValueError(f"x0 must be [d] = [{d}] or [B, d] = [{bsz}, {d}], got {list(x0.shape)}")

    def _initial_cov(self, P0, bsz, d, dtype, device) -> Tensor:
        if P0 is None:
            return _as_matrix(self.init_var, d, "init_var", dtype, device).expand(bsz, d, d)
        P0 = torch.as_tensor(P0).to(dtype=dtype, device=device)
        if P0.ndim == 2:
            P0 = P0.expand(bsz, d, d)
        if P0.ndim != 3 or P0.shape != (bsz, d, d):
            raise ValueError(f"P0 must be [d, d] or [B, d, d] with B={bsz}, d={d}, got {list(P0.shape)}")
        sym = P0.detach()
        if not torch.allclose(sym, sym.transpose(-1, -2), rtol=1e-5, atol=1e-8):
            raise ValueError("P0 must be symmetric; symmetrise it, e.g. (P0 + P0.transpose(-1, -2)) / 2")
        if bool((torch.linalg.cholesky_ex(sym)[1] != 0).any()):
            raise ValueError(
                "P0 must be positive definite (its Cholesky failed for some trajectories): add a multiple of "
                "the identity or use the default init_var * I"
            )
        return P0
