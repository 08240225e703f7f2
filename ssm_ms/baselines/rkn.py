"""Recurrent Kalman Network (RKN), after Becker et al., *Recurrent Kalman Networks: Factorized Inference in
High-Dimensional Deep Feature Spaces* (ICML 2019): the baseline of the paper's tables.

Only the torch networks; training (loss, optimiser, logging) lives elsewhere. Written from the paper, with
the details the paper leaves open (initialisation, default sizes) taken from the authors' reference code
and marked "(RKN code)" below; our own choices are marked "(ours)".

Model. An encoder maps each frame ``y[t]`` to a *latent observation* ``w`` (size ``m``, L2-normalised per
sample) with a variance ``s`` (``elu(.) + 1``). The latent state ``z`` has size ``n = 2m``: an *observation
part* (upper half, observed through ``H = [I_m, 0]``) and a *memory part* (lower half). Its covariance is
factorised into three diagonal ``m x m`` blocks, kept as vectors (:class:`FactorizedCovariance`)::

    Sigma = [[diag(upper), diag(side) ],
             [diag(side),  diag(lower)]]

With this structure and ``H = [I, 0]`` the Kalman update needs no matrix inversion and keeps the structure
exactly (:func:`rkn_update`). The transition is locally linear, ``A(z) = sum_k alpha_k(z) A^(k)`` with ``K``
band-structured basis matrices, ``alpha = softmax(net(z))``; the prior covariance keeps only the diagonals
of the blocks of ``A Sigma A^T + Q`` (:func:`rkn_predict`, the RKN's approximation). A decoder maps the
posterior to the measurement: transposed convolutions with a sigmoid for images, or, for vectors, a mean
MLP of the posterior mean and a variance MLP of the covariance vectors (the paper's Gaussian decoder).

Convention (:meth:`RecurrentKalmanNetwork.filter`)::

    prior (mean 0, upper = lower = initial_cov, side = 0) for time 0
    for t in 0..T-1:  update with (w[t], s[t]) where observed[:, t]  -> posterior at t
                      (skipped where not observed: posterior = prior)
                      predict through A(posterior mean)               -> prior for t+1 (not after the last step)

The output at ``t`` decodes the posterior at ``t``: a filtered estimate where ``y[t]`` was observed, a
prediction from the last observed frame where it was not.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ssm_ms.baselines.common import SequenceOutput, frame_encoder, image_decoder, preset_for


class FactorizedCovariance(NamedTuple):
    """The RKN's covariance of the latent state ``[upper; lower]``: diagonals of its three ``m x m`` blocks.

    ``upper [..., m]``: diag of the observation part's covariance; ``lower [..., m]``: of the memory part's;
    ``side [..., m]``: of the cross-covariance between them (may be negative).
    """

    upper: Tensor
    lower: Tensor
    side: Tensor


class RKNFilterResult(NamedTuple):
    """Latent posteriors of :meth:`RecurrentKalmanNetwork.filter`.

    ``means [B, T, 2m]`` and ``covs`` (a :class:`FactorizedCovariance` of ``[B, T, m]`` tensors).
    """

    means: Tensor
    covs: FactorizedCovariance


def elup1(x: Tensor) -> Tensor:
    """``elu(x) + 1``: a positive, smooth map (``exp(x)`` below 0, ``x + 1`` above); the RKN's variance activation."""
    return F.elu(x) + 1.0


def elup1_inverse(y: float) -> float:
    """The ``x`` with ``elu(x) + 1 = y`` (``y > 0``)."""
    if y <= 0:
        raise ValueError(f"elu + 1 only takes positive values, got {y}")
    return y - 1.0 if y >= 1.0 else math.log(y)


def band_mask(size: int, bandwidth: int) -> Tensor:
    """``[size, size]`` float mask, 1 where ``|i - j| <= bandwidth``."""
    idx = torch.arange(size)
    return ((idx[:, None] - idx[None, :]).abs() <= bandwidth).float()


def _matvec(a: Tensor, v: Tensor) -> Tensor:
    """Batched ``a [..., m, m] @ v [..., m]``."""
    return (a @ v.unsqueeze(-1)).squeeze(-1)


def rkn_update(
    mean: Tensor, cov: FactorizedCovariance, w: Tensor, w_var: Tensor, valid: Tensor | None = None
) -> tuple[Tensor, FactorizedCovariance]:
    """The RKN's Kalman update with ``H = [I_m, 0]`` and ``R = diag(w_var)``, in closed form (no inversion).

    With ``q_u = upper / (upper + s)`` and ``q_l = side / (upper + s)``::

        mean_u += q_u (w - mean_u),  mean_l += q_l (w - mean_u)
        upper' = (1 - q_u) upper,    lower' = lower - q_l side,   side' = (1 - q_u) side

    This is the exact Kalman update of the block-diagonal-blocks covariance (whose posterior has the same
    structure). Elementwise, so any leading dimensions broadcast.

    Args:
        mean: prior mean ``[..., 2m]`` (upper half: observation part, lower half: memory part).
        cov: prior :class:`FactorizedCovariance`, each ``[..., m]``.
        w: latent observation ``[..., m]``; w_var: its variance ``[..., m]`` (positive).
        valid: optional ``[...]`` bool: where False the posterior is the prior exactly (missing measurement),
            and ``w``/``w_var`` there have no influence (not even on gradients).

    Returns:
        posterior ``(mean, cov)``.
    """
    m = w.shape[-1]
    if mean.shape[-1] != 2 * m:
        raise ValueError(
            f"the state mean has {mean.shape[-1]} components but the latent observation {m}: needs 2 * {m}"
        )
    upper, lower, side = cov
    if valid is not None:
        # keep invalid w / w_var out of every computation (NaN or inf there must not reach the gradients)
        v = valid.unsqueeze(-1)
        w = torch.where(v, w, mean[..., :m].detach())
        w_var = torch.where(v, w_var, torch.ones_like(w_var))
    denom = upper + w_var
    q_u = upper / denom
    q_l = side / denom
    residual = w - mean[..., :m]
    new_mean = mean + torch.cat([q_u * residual, q_l * residual], dim=-1)
    keep = 1.0 - q_u
    new_cov = FactorizedCovariance(keep * upper, lower - q_l * side, keep * side)
    if valid is None:
        return new_mean, new_cov
    v = valid.unsqueeze(-1)
    new_mean = torch.where(v, new_mean, mean)
    new_cov = FactorizedCovariance(*(torch.where(v, new, old) for new, old in zip(new_cov, cov)))
    return new_mean, new_cov


def rkn_predict(
    mean: Tensor,
    cov: FactorizedCovariance,
    a11: Tensor,
    a12: Tensor,
    a21: Tensor,
    a22: Tensor,
    noise_upper: Tensor,
    noise_lower: Tensor,
) -> tuple[Tensor, FactorizedCovariance]:
    """The RKN's prediction through ``A = [[a11, a12], [a21, a22]]`` with noise ``Q = diag(noise_upper, noise_lower)``.

    Mean ``A z``; covariance: the diagonals of the three blocks of ``A Sigma A^T + Q``, where ``Sigma`` has the
    three diagonal blocks of ``cov`` (the off-diagonal entries of the blocks are dropped, the RKN's
    approximation)::

        upper_i = sum_j a11_ij^2 u_j + 2 a11_ij a12_ij s_j + a12_ij^2 l_j + q_u,i
        lower_i = sum_j a21_ij^2 u_j + 2 a21_ij a22_ij s_j + a22_ij^2 l_j + q_l,i
        side_i  = sum_j a21_ij a11_ij u_j + (a22_ij a11_ij + a21_ij a12_ij) s_j + a22_ij a12_ij l_j

    Args:
        mean: ``[B, 2m]``; cov: :class:`FactorizedCovariance` of ``[B, m]``.
        a11, a12, a21, a22: per-sample blocks ``[B, m, m]``.
        noise_upper, noise_lower: transition noise variances ``[m]`` or ``[B, m]``.
    """
    m = a11.shape[-1]
    if mean.shape[-1] != 2 * m:
        raise ValueError(f"the state mean has {mean.shape[-1]} components but the transition blocks are {m} x {m}")
    # All of it in two batched products (the filter runs this once per time step: few large ops beat many
    # small ones): rows [a11 a12; a21 a22] give the mean; the coefficients of (u, s, l) in the three
    # diagonals, stacked as one [3m, 3m] matrix per sample, give the covariance.
    left = torch.cat([a11, a21], dim=-2)  # [B, 2m, m]: the columns acting on the upper half
    right = torch.cat([a12, a22], dim=-2)  # [B, 2m, m]: on the lower half
    new_mean = _matvec(torch.cat([left, right], dim=-1), mean)
    diagonals = torch.cat([left * left, 2.0 * left * right, right * right], dim=-1)  # [B, 2m, 3m]
    sides = torch.cat([a21 * a11, a22 * a11 + a21 * a12, a22 * a12], dim=-1)  # [B, m, 3m]
    moments = _matvec(torch.cat([diagonals, sides], dim=-2), torch.cat([cov.upper, cov.side, cov.lower], dim=-1))
    noise = torch.cat([noise_upper.expand_as(cov.upper), noise_lower.expand_as(cov.lower)], dim=-1)
    new_diag = moments[..., : 2 * m] + noise
    return new_mean, FactorizedCovariance(new_diag[..., :m], new_diag[..., m:], moments[..., 2 * m :])


def _mlp(in_features: int, hidden: Sequence[int], out_features: int, activation: type[nn.Module]) -> nn.Sequential:
    layers: list[nn.Module] = []
    width = in_features
    for h in hidden:
        layers += [nn.Linear(width, int(h)), activation()]
        width = int(h)
    layers.append(nn.Linear(width, out_features))
    return nn.Sequential(*layers)


_ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "relu": nn.ReLU}


class RKNTransition(nn.Module):
    """The RKN's locally linear transition with learned noise: ``(posterior mean, cov) -> (prior mean, cov)``.

    ``A(z) = sum_k alpha_k(z) A^(k)``, ``alpha = softmax(net(z))`` of the full posterior mean ``z [B, 2m]``.
    Each basis matrix ``A^(k) = [[B11, B12], [B21, B22]]`` has four ``m x m`` band blocks (entries with
    ``|i - j| <= bandwidth``; the others are exactly zero, by a fixed mask applied to the raw parameters, so
    also after any optimiser step). Initialisation (RKN code): ``B11 = B22 = I + 0``, ``B12 = 0.2 I``,
    ``B21 = -0.2 I`` for every ``k``, i.e. at initialisation ``A = [[I, 0.2 I], [-0.2 I, I]]`` whatever alpha.
    The identity of ``B11`` and ``B22`` is fixed; the learned parameters are the band entries of the
    deviations from it (of ``B12``, ``B21`` themselves).

    Transition noise ``Q = diag(q_upper, q_lower)``: one variance per latent dimension, ``elu(raw) + 1``,
    each starting at ``initial_transition_var`` (0.1, the RKN code's ``trans_covar``).

    Args:
        latent_obs_dim: ``m`` (the state has ``2m`` components).
        n_basis: number of basis matrices ``K`` (RKN default 15).
        bandwidth: band half-width of the blocks (RKN default 3).
        coeff_hidden: hidden widths of the coefficient network; ``()`` (RKN default): one linear layer
            ``2m -> K`` then softmax.
        coeff_activation: activation of its hidden layers, ``"tanh"`` (RKN code's default) or ``"relu"``.
        initial_transition_var: initial value of every transition noise variance.
    """

    def __init__(
        self,
        latent_obs_dim: int,
        n_basis: int = 15,
        bandwidth: int = 3,
        coeff_hidden: Sequence[int] = (),
        coeff_activation: str = "tanh",
        initial_transition_var: float = 0.1,
    ):
        super().__init__()
        m = int(latent_obs_dim)
        if m < 1 or n_basis < 1:
            raise ValueError(f"latent_obs_dim and n_basis must be >= 1, got {latent_obs_dim}, {n_basis}")
        if bandwidth < 0:
            raise ValueError(f"bandwidth must be >= 0 (0: diagonal blocks), got {bandwidth}")
        if any(int(h) < 1 for h in coeff_hidden):
            raise ValueError(f"coeff_hidden widths must be >= 1, got {list(coeff_hidden)}")
        if coeff_activation not in _ACTIVATIONS:
            raise ValueError(f"coeff_activation must be one of {sorted(_ACTIVATIONS)}, got {coeff_activation!r}")
        if not initial_transition_var > 0:
            raise ValueError(f"initial_transition_var must be > 0 (a variance), got {initial_transition_var}")
        self.latent_obs_dim, self.n_basis, self.bandwidth = m, int(n_basis), int(bandwidth)
        self.register_buffer("band", band_mask(m, bandwidth), persistent=False)
        self.register_buffer("eye", torch.eye(m), persistent=False)
        eye = torch.eye(m).expand(n_basis, m, m)
        self.b11 = nn.Parameter(torch.zeros(n_basis, m, m))  # deviation from I
        self.b12 = nn.Parameter(0.2 * eye.clone())
        self.b21 = nn.Parameter(-0.2 * eye.clone())
        self.b22 = nn.Parameter(torch.zeros(n_basis, m, m))  # deviation from I
        self.coefficient_net = nn.Sequential(
            _mlp(2 * m, coeff_hidden, n_basis, _ACTIVATIONS[coeff_activation]), nn.Softmax(dim=-1)
        )
        raw = elup1_inverse(float(initial_transition_var))
        self.raw_noise_upper = nn.Parameter(torch.full((m,), raw))
        self.raw_noise_lower = nn.Parameter(torch.full((m,), raw))

    def basis(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The basis blocks ``(B11, B12, B21, B22)``, each ``[K, m, m]``, band-masked, identity included."""
        band, eye = self.band, self.eye
        return self.b11 * band + eye, self.b12 * band, self.b21 * band, self.b22 * band + eye

    def coefficients(self, mean: Tensor) -> Tensor:
        """``alpha [B, K]`` (rows sum to 1) at the posterior means ``[B, 2m]``."""
        return self.coefficient_net(mean)

    def transition_matrices(self, mean: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The blocks ``(a11, a12, a21, a22)`` of ``A(mean)``, each ``[B, m, m]``."""
        m, k = self.latent_obs_dim, self.n_basis
        stacked = torch.stack(self.basis(), dim=1).reshape(k, 4 * m * m)  # [K, 4 m m]
        mixed = (self.coefficients(mean) @ stacked).view(*mean.shape[:-1], 4, m, m)
        return mixed[..., 0, :, :], mixed[..., 1, :, :], mixed[..., 2, :, :], mixed[..., 3, :, :]

    def noise(self) -> tuple[Tensor, Tensor]:
        """Transition noise variances ``(q_upper [m], q_lower [m])``, positive."""
        return elup1(self.raw_noise_upper), elup1(self.raw_noise_lower)

    def forward(self, mean: Tensor, cov: FactorizedCovariance) -> tuple[Tensor, FactorizedCovariance]:
        """Posterior ``(mean [B, 2m], cov)`` at ``t`` -> prior ``(mean, cov)`` at ``t + 1``."""
        return rkn_predict(mean, cov, *self.transition_matrices(mean), *self.noise())


class RecurrentKalmanNetwork(nn.Module):
    """The Recurrent Kalman Network: encoder, factorised Kalman filter in a learned latent space, decoder.

    ``forward(y [B, T, *obs_shape], observed [B, T] bool) -> SequenceOutput(mean, var)``: the estimate of
    every ``y[t]`` from the observed frames up to ``t`` (see the module docstring for the recursion).

    Args:
        obs_shape: one measurement: ``[C, H, W]`` images or ``[D]`` vectors.
        latent_state_dim: ``n = 2m``, must be even (upper and lower halves); 30 is ours.
        n_basis, bandwidth, coeff_hidden, coeff_activation, initial_transition_var: the transition, see
            :class:`RKNTransition` (defaults of the RKN code: 15, 3, ``()``, tanh, 0.1).
        encoder_preset: preset of the per-frame CNN (:class:`~ssm_ms.nets.encoder.FrameEncoder`):
            ``None`` picks ``"vector"`` for vectors and, for images, by size (ours): 24 -> ``"pendulum"``,
            48 -> ``"quad"``, 64 -> ``"mnist"`` (other square sizes: the nearest of these); or the CNN itself as
            a mapping, as :class:`~ssm_ms.baselines.lstm.Seq2SeqLSTM`'s.
        encoder_hidden: widths of Linear + ReLU layers between the CNN features and the two heads of
            ``w`` (``m``) and ``s`` (``m``, ``elu + 1``); ``()`` by default (ours).
        decoder_preset: images only: the :class:`~ssm_ms.nets.decoder.ConvDecoder` preset; ``None``
            picks it by size like the encoder; or the layers as a mapping, as ``Seq2SeqLSTM``'s. It draws the
            image size of ``obs_shape``; its channels must match (checked here).
        decoder_hidden: vectors only: ReLU hidden widths of the mean MLP (of the posterior mean) and of the
            variance MLP (of ``[upper, lower, side]``); ``(64,)`` by default (ours).
        initial_cov: initial ``upper`` and ``lower`` variances (10, the RKN code's ``initial_state_covar``);
            initial mean 0, side 0. Fixed here (ours: the RKN code can also learn it).
        normalize_latent_obs: L2-normalise ``w`` per sample (RKN paper and code).
        output: ``"auto"`` (``"sigmoid"`` for images, ``"gaussian"`` for vectors), or ``"sigmoid"`` /
            ``"linear"`` for images (no variance), ``"gaussian"`` / ``"linear"`` (mean only) for vectors.
    """

    def __init__(
        self,
        obs_shape: Sequence[int],
        latent_state_dim: int = 30,
        n_basis: int = 15,
        bandwidth: int = 3,
        coeff_hidden: Sequence[int] = (),
        encoder_preset: str | Mapping[str, Any] | None = None,
        encoder_hidden: Sequence[int] = (),
        decoder_preset: str | Mapping[str, Any] | None = None,
        decoder_hidden: Sequence[int] = (64,),
        initial_cov: float = 10.0,
        normalize_latent_obs: bool = True,
        output: str = "auto",
        coeff_activation: str = "tanh",
        initial_transition_var: float = 0.1,
    ):
        super().__init__()
        obs_shape = tuple(int(s) for s in obs_shape)
        if len(obs_shape) not in (1, 3):
            raise ValueError(f"obs_shape must be [C, H, W] (images) or [D] (vectors), got {list(obs_shape)}")
        n = int(latent_state_dim)
        if n < 2 or n % 2:
            lo, hi = max(2, n - n % 2), n + 2 - n % 2
            fix = f"use {lo} or {hi}" if n % 2 and n > 1 else "use 2 or more"
            raise ValueError(
                f"latent_state_dim must be even and >= 2 (an observation half and a memory half of equal size), "
                f"got {latent_state_dim}: {fix}"
            )
        if not initial_cov > 0:
            raise ValueError(f"initial_cov must be > 0 (a variance), got {initial_cov}")
        is_image = len(obs_shape) == 3
        if output == "auto":
            output = "sigmoid" if is_image else "gaussian"
        allowed = ("sigmoid", "linear") if is_image else ("gaussian", "linear")
        if output not in allowed:
            kind = "images" if is_image else "vectors"
            raise ValueError(f"output for {kind} must be 'auto' or one of {list(allowed)}, got {output!r}")
        m = n // 2
        self.obs_shape, self.latent_state_dim, self.latent_obs_dim = obs_shape, n, m
        self.output, self.normalize_latent_obs = output, bool(normalize_latent_obs)
        self.initial_cov = float(initial_cov)

        # --- encoder: frame -> (w, s)
        if encoder_preset is None:
            encoder_preset = preset_for(obs_shape, "encoder_preset") if is_image else "vector"
        self.encoder = frame_encoder(obs_shape, encoder_preset)
        if any(int(h) < 1 for h in encoder_hidden):
            raise ValueError(f"encoder_hidden widths must be >= 1, got {list(encoder_hidden)}")
        layers: list[nn.Module] = []
        width = self.encoder.out_features
        for h in encoder_hidden:
            layers += [nn.Linear(width, int(h)), nn.ReLU()]
            width = int(h)
        self.encoder_hidden = nn.Sequential(*layers)
        self.w_head = nn.Linear(width, m)
        self.w_var_head = nn.Linear(width, m)

        # --- transition
        self.transition = RKNTransition(m, n_basis, bandwidth, coeff_hidden, coeff_activation, initial_transition_var)

        # --- decoder
        self.decoder_var: nn.Module | None = None
        if is_image:
            self.decoder: nn.Module = image_decoder(n, obs_shape, decoder_preset, output)
        else:
            if any(int(h) < 1 for h in decoder_hidden):
                raise ValueError(f"decoder_hidden widths must be >= 1, got {list(decoder_hidden)}")
            self.decoder = _mlp(n, decoder_hidden, obs_shape[0], nn.ReLU)
            if output == "gaussian":
                self.decoder_var = _mlp(3 * m, decoder_hidden, obs_shape[0], nn.ReLU)

    # ------------------------------------------------------------------------------------------------
    def encode(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """Frames ``[..., *obs_shape]`` -> latent observations ``w [..., m]`` and their variances ``s [..., m]``."""
        h = self.encoder_hidden(self.encoder(y))
        w = self.w_head(h)
        if self.normalize_latent_obs:
            w = F.normalize(w, p=2.0, dim=-1, eps=1e-12)
        return w, elup1(self.w_var_head(h))

    def initial_state(
        self, batch: int, dtype: torch.dtype | None = None, device: torch.device | None = None
    ) -> tuple[Tensor, FactorizedCovariance]:
        """The prior at time 0: mean 0 ``[batch, 2m]``; upper = lower = ``initial_cov``, side = 0 ``[batch, m]``."""
        p = self.w_head.weight
        dtype, device = dtype or p.dtype, device or p.device
        m = self.latent_obs_dim
        full = torch.full((batch, m), self.initial_cov, dtype=dtype, device=device)
        return (
            torch.zeros(batch, 2 * m, dtype=dtype, device=device),
            FactorizedCovariance(full, full.clone(), torch.zeros(batch, m, dtype=dtype, device=device)),
        )

    def _check_inputs(self, y: Tensor, observed: Tensor | None) -> Tensor:
        k = len(self.obs_shape)
        if y.dim() != 2 + k or tuple(y.shape[2:]) != self.obs_shape:
            raise ValueError(
                f"y must be [B, T, {', '.join(map(str, self.obs_shape))}] "
                f"(batch, time, obs_shape {list(self.obs_shape)}), "
                f"got {list(y.shape)}"
            )
        b, t = y.shape[:2]
        if t < 1:
            raise ValueError(f"y needs at least one time step, got {list(y.shape)}")
        if observed is None:
            return torch.ones(b, t, dtype=torch.bool, device=y.device)
        if tuple(observed.shape) != (b, t):
            raise ValueError(
                f"observed must be [B, T] = [{b}, {t}] like y's first two dimensions, got {list(observed.shape)}"
            )
        if observed.dtype != torch.bool:
            observed = observed != 0
        return observed.to(y.device)

    def filter(self, y: Tensor, observed: Tensor | None = None) -> RKNFilterResult:
        """Latent posteriors: ``means [B, T, 2m]`` and ``covs`` (:class:`FactorizedCovariance`, ``[B, T, m]``).

        ``observed [B, T]`` (bool, default all True): where False, ``y[:, t]`` is ignored (zeroed before
        encoding, so even NaN there has no effect) and the update is skipped.
        """
        observed = self._check_inputs(y, observed)
        b, t = observed.shape
        mask = observed.view(b, t, *([1] * len(self.obs_shape)))
        y = torch.where(mask, y, torch.zeros((), dtype=y.dtype, device=y.device))
        w, w_var = self.encode(y)  # all frames in one call: [B, T, m]
        mean, cov = self.initial_state(b, dtype=w.dtype, device=w.device)
        means, covs = [], []
        for i in range(t):
            mean, cov = rkn_update(mean, cov, w[:, i], w_var[:, i], observed[:, i])
            means.append(mean)
            covs.append(cov)
            if i < t - 1:
                mean, cov = self.transition(mean, cov)
        stacked = FactorizedCovariance(*(torch.stack(parts, dim=1) for parts in zip(*covs)))
        return RKNFilterResult(torch.stack(means, dim=1), stacked)

    def decode(self, means: Tensor, covs: FactorizedCovariance) -> SequenceOutput:
        """Posteriors ``means [..., 2m]``, ``covs`` (``[..., m]`` each) -> ``SequenceOutput`` ``[..., *obs_shape]``."""
        mean = self.decoder(means)  # ConvDecoder and the MLP both keep the leading dimensions
        var = None
        if self.decoder_var is not None:
            var = elup1(self.decoder_var(torch.cat(tuple(covs), dim=-1)))
        return SequenceOutput(mean, var)

    def forward(self, y: Tensor, observed: Tensor | None = None) -> SequenceOutput:
        """``y [B, T, *obs_shape]``, ``observed [B, T]`` -> estimates ``mean [B, T, *obs_shape]`` (and ``var``)."""
        result = self.filter(y, observed)
        return self.decode(result.means, result.covs)
