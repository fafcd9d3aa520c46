"""Particle filters on the library's :class:`~prognos_torch.core.model.StateSpaceModel`.

Model (additive Gaussian noise, :mod:`prognos_torch.core.model`)::

    x_k = f(x_{k-1}, u_k, k) + w_k,  w_k ~ N(q_k, Q_k);   y_k = h(x_k, u_k, k) + v_k,  v_k ~ N(r_k, R_k)

Particles have shape ``(..., N, n)``: the leading dims ``...`` are independent runs (Monte Carlo
runs, assets), ``N`` the particle count. Log-weights ``(..., N)`` are kept normalised
(``logsumexp = 0``). All randomness comes from an explicit ``torch.Generator``.

Variants (one :class:`ParticleFilter` configuration each, one step function; the factories
:func:`sir`, :func:`ekpf`, :func:`upf`, :func:`stpf` are in :mod:`prognos_torch.filters.variants`):

- **SIR / bootstrap** (``proposal=None``): ``x_k^i ~ p(x_k | x_{k-1}^i)``,
  ``w_k^i ∝ w_{k-1}^i p(y_k | x_k^i)``.
- **Gaussian-proposal PFs** (``proposal=`` a :class:`~prognos_torch.filters.gaussian.GaussianFilter`):
  every particle carries its own Gaussian ``N(x_{k-1}^i, P_{k-1}^i)`` (the engine's
  :class:`~prognos_torch.filters.gaussian.FilterState` with the particles as a batch dimension).
  ONE engine step with ``y_k`` gives ``N(xbar_k^i, Phat_k^i)``; the particle is drawn from it and
  reweighted by

      w_k^i ∝ w_{k-1}^i p(y_k | x_k^i) p(x_k^i | x_{k-1}^i) / q(x_k^i | x_{k-1}^i, y_k)

  (paper 002, STPF step 3; Van der Merwe et al., "The unscented particle filter", 2000, Sec. 4).
  The carried covariance becomes ``Phat_k^i`` and the mean is replaced by the drawn particle, as in
  the UPF/EKPF of Van der Merwe et al. With :func:`ekf` this is the EKPF (de Freitas et al.),
  with :func:`ukf`/:func:`srukf` the UPF, and with the strong-tracking EKF (SFEKF, :func:`stekf`,
  whose ``FilterState.fading`` holds each particle's ``V_k``) the **STPF** of paper 002
  (Eq. 27, steps 1-7).

Paper 002, Eq. 27 reads ``q(x_k^i | x_{k-1}^i, y_k) = N(xhat_{k+1|k}^i, P_{k+1|k}^i)``; the
indices are garbled in the extracted text (and the surrounding sentence calls it "the
approximate posterior state pdf", and step 2 says SFEKF *updates* each particle with ``y_k``).
We use the SFEKF posterior ``N(xhat_{k|k}^i, P_{k|k}^i)``, the standard EKPF/UPF choice, which
is what step 2 describes. Step 6 of the paper redraws particles from the per-particle Gaussians
when resampling; that would leave the weights wrong (the draw is not from the weighted target),
so we resample ancestors (particles, their Gaussians and fading states together) instead.

Missing measurements (a ``y_k`` with NaN throughout, per run): the particles are only
propagated through ``p(x_k | x_{k-1})`` and the weights are unchanged; the carried Gaussians are
predicted. A partly NaN ``y_k`` weights by ``p(y_{k,o} | x_k)``, the density of its observed
components ``o`` (Gaussian, covariance ``R_oo``), and a Gaussian proposal updates with them.

Robustness: a particle whose proposal Gaussian is not finite or not positive definite is drawn
from the transition prior instead (a valid per-particle proposal; counted in
``prior_fallback``); non-finite particles or weight increments get zero weight. When every
weight of a run is zero or non-finite (weight collapse), a :class:`WeightCollapseWarning` is
issued and that run's weights are reset to uniform over its finite particles; its
log-likelihood increment is then ``-inf`` (the estimate of ``p(y_k | y_{1:k-1})`` is 0).
Estimates are therefore never NaN unless every particle of a run is non-finite, which raises
``FloatingPointError``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..core.belief import GaussianBelief, check_belief
from ..core.model import StateSpaceModel
from ..core.random import standard_normal
from ..core.validation import (
    all_finite,
    check_control,
    check_generator,
    check_measurement,
    check_nonneg_int,
    check_sequence,
    has_missing,
    is_int,
    is_real,
    plain_number,
)
from ._particle_blocks import (
    _UNIFORM_CHECK,
    ParticleState,
    _estimates,
    _log_normaliser,
    _resample_flags,
    _resample_some,
)
from ._particle_compiled import check_compilable, compiled_run
from ._particle_noise import (
    _LOG_2PI,
    _constant_noise,
    _gauss_logpdf,
    _noise,
    _observed_logpdf,
    _particle_model,
    _PNoise,
    _Setup,
    _sum_last,
)
from ._particle_trees import _check_ancestors, _gather, gather_particles, where_particles
from .gaussian import GaussianFilter, Taylor
from .resampling import Resampler, _draw_ancestors, get_resampler
from .sequence import scan

__all__ = [
    "ParticleFilter",
    "ParticleState",
    "ParticleStepInfo",
    "ParticleTrajectory",
    "WeightCollapseWarning",
    "ProposalFallbackWarning",
    "gather_particles",
    "where_particles",
]

#: from this many particle values the step's finite test sums each part instead of
#: concatenating them first
_SUM_PARTS_MIN = 8192


def _host_float(t: Tensor) -> float:
    """A one-element tensor read on the host for a decision (no gradient flows through it, and
    autograd's warning about a scalar read of a differentiable tensor does not apply)."""
    return float(t.detach() if t.requires_grad else t)


def _check_log_weights(lw: Tensor) -> None:
    """Refuse log-weights ``(..., N)`` that are no normalised distribution (NaN or ``+inf``, a
    run all ``-inf``, a log-sum off 0 by more than ``1e-6 + 4 N eps``, the tolerance of
    :func:`~prognos_torch.core.validation.check_weights`): the step's likelihood estimate
    ``log sum_i w_i p(y | x_i)`` reads them as normalised, and weights are never renormalised
    silently. One host read."""
    lse = torch.logsumexp(lw.detach(), -1)
    dev = _host_float(lse.abs().amax()) if lse.numel() else 0.0
    if dev <= 1e-6 + 4.0 * lw.shape[-1] * torch.finfo(lw.dtype).eps:
        return
    if bool(torch.isnan(lw).any()) or bool((lw == math.inf).any()):
        raise ValueError("state.log_weights must not contain NaN or +inf")
    if bool(torch.isneginf(lse).any()):
        raise ValueError(
            "state.log_weights are -inf for every particle of a run (no weighted particle set)"
        )
    raise ValueError(
        f"state.log_weights must be normalised (logsumexp over the particles 0), got a log-sum "
        f"off by up to {dev:.3g}; pass log_weights - log_weights.logsumexp(-1, keepdim=True)"
    )


class WeightCollapseWarning(RuntimeWarning):
    """Every particle weight of a run was zero or non-finite; the weights were reset."""


class ProposalFallbackWarning(RuntimeWarning):
    """Some per-particle Gaussian proposals were invalid; those particles used the prior."""


# ---------------------------------------------------------------------- state and outputs
@dataclass(frozen=True)
class ParticleStepInfo:
    """Diagnostics of one particle-filter step (batch dims ``...``).

    Attributes:
        mean: ``(..., n)`` weighted posterior mean ``sum_i w_k^i x_k^i`` (paper 002 step 5).
        cov: ``(..., n, n)`` weighted posterior covariance.
        ess: ``(...)`` effective sample size ``1 / sum_i (w_k^i)^2`` before resampling.
        resampled: ``(...)`` bool, whether the run was resampled after this step.
        log_likelihood: ``(...)`` estimate of ``log p(y_k | y_{1:k-1})`` (0 where missing).
        collapsed: ``(...)`` bool, weight collapse (weights reset, see module docstring).
        prior_fallback: ``(...)`` number of particles drawn from the prior because their
            Gaussian proposal was invalid.
        fading_factor: ``(...)`` weighted mean of the particles' fading factors ``lambda_k``
            (1 without strong tracking).
        missing: ``(...)`` bool: no component observed (propagated only).
        particles: ``(..., N, n)`` the weighted particle set before resampling.
        log_weights: ``(..., N)`` its normalised log-weights.
    """

    mean: Tensor
    cov: Tensor
    ess: Tensor
    resampled: Tensor
    log_likelihood: Tensor
    collapsed: Tensor
    prior_fallback: Tensor
    fading_factor: Tensor
    missing: Tensor
    particles: Tensor
    log_weights: Tensor

    @property
    def std(self) -> Tensor:
        return torch.diagonal(self.cov, dim1=-2, dim2=-1).sqrt()


@dataclass(frozen=True)
class ParticleTrajectory:
    """Particle-filter output over ``T`` steps (time leading, batch dims after it).

    Attributes:
        means: ``(T, ..., n)``; covs: ``(T, ..., n, n)``.
        ess: ``(T, ...)`` before resampling; resampled, collapsed, missing: ``(T, ...)`` bool.
        log_likelihoods: ``(T, ...)`` per-step estimates; ``log_likelihood`` their sum.
        prior_fallback: ``(T, ...)`` counts; fading_factors: ``(T, ...)``.
        particles, log_weights: ``(T, ..., N, n)``/``(T, ..., N)`` before resampling (only with
            ``keep_particles=True``, else ``None``).
        final: the :class:`ParticleState` after the last step (resume from it).
    """

    means: Tensor
    covs: Tensor
    ess: Tensor
    resampled: Tensor
    log_likelihoods: Tensor
    collapsed: Tensor
    prior_fallback: Tensor
    fading_factors: Tensor
    missing: Tensor
    particles: Tensor | None
    log_weights: Tensor | None
    final: ParticleState

    @property
    def stds(self) -> Tensor:
        return torch.diagonal(self.covs, dim1=-2, dim2=-1).sqrt()

    @property
    def log_likelihood(self) -> Tensor:
        return self.log_likelihoods.sum(0)


# ---------------------------------------------------------------------- the filter
@dataclass(frozen=True)
class ParticleFilter:
    """A particle-filter configuration (see the module docstring).

    Attributes:
        num_particles: ``N >= 1``.
        proposal: ``None`` (bootstrap SIR) or a Gaussian filter run per particle for the proposal.
        resample_threshold: resample a run when ``N_eff < resample_threshold * N``, in
            ``[0, 1]`` (paper 002 step 6: ``1/3``; ``0`` never resamples; ``1`` resamples
            whenever the weights are not uniform).
        resampler: ``"systematic"``, ``"stratified"``, ``"residual"``, ``"multinomial"`` or a
            callable ``(log_w (..., N), generator) -> ancestors (..., N)``.
        name: label for tables.
    """

    num_particles: int = 1000
    proposal: GaussianFilter | None = None
    resample_threshold: float = 0.5
    resampler: str | Resampler = "systematic"
    name: str = ""

    def __post_init__(self):
        N = self.num_particles
        if not is_int(N) or N < 1:
            raise ValueError(f"num_particles must be a positive int, got {N!r}")
        thr = self.resample_threshold
        if not is_real(thr) or not 0.0 <= thr <= 1.0:
            raise ValueError(f"resample_threshold must be a number in [0, 1], got {thr!r}")
        # NumPy scalars as the Python numbers they are: a numpy.float32 threshold times N was
        # rounded to float32 (0.3 * 1000 = 300.0, not 300.0000119) and moved the decision
        object.__setattr__(self, "num_particles", plain_number(N))
        object.__setattr__(self, "resample_threshold", plain_number(thr))
        if self.proposal is not None and not isinstance(self.proposal, GaussianFilter):
            raise TypeError(
                "proposal must be None (bootstrap) or a GaussianFilter (e.g. ekf(), ukf(), "
                f"stekf()), got {type(self.proposal).__name__}"
            )
        get_resampler(self.resampler)  # validates names

    # ------------------------------------------------------------------ init
    def init(
        self,
        model: StateSpaceModel,
        belief: GaussianBelief,
        *,
        generator: torch.Generator,
        k: int = 0,
    ) -> ParticleState:
        """Draw ``N`` particles ``x_0^i ~ N(mean, chol chol^T)`` with weights ``1/N`` (paper 002
        STPF step 1); Gaussian-proposal PFs give each particle the covariance ``P_0``.

        Args:
            belief: ``mean (..., n)``, ``chol (..., n, n)``; its batch dims are the runs.
            generator: on the belief's device.
            k: step index of the first measurement minus one (noise of step ``k + 1`` is used
                to initialise noise estimators, as in :func:`prognos_torch.filters.run`).
        Returns:
            :class:`ParticleState` with particles ``(..., N, n)``.
        """
        check_belief(belief, model.state_dim)
        mean, chol = belief.mean, belief.chol
        check_generator(generator, mean)
        bs, n, N = belief.batch_shape, model.state_dim, self.num_particles
        eps = standard_normal((*bs, N, n), generator, mean.dtype, mean.device)
        x0 = mean.unsqueeze(-2) + eps @ chol.mT
        lw = torch.full((*bs, N), -math.log(N), dtype=mean.dtype, device=mean.device)
        fs = None
        if self.proposal is not None:
            pb = GaussianBelief(x0, chol.unsqueeze(-3).expand(*bs, N, n, n).clone())
            fs = self.proposal.init(_particle_model(model, len(bs), N), pb, k + 1)
        return ParticleState(x0, lw, fs)

    # ------------------------------------------------------------------ checks
    def _check_state(self, model, state) -> None:
        if not isinstance(state, ParticleState):
            raise TypeError(f"state must be a ParticleState, got {type(state).__name__}")
        x, lw = state.particles, state.log_weights
        if not isinstance(x, Tensor) or not isinstance(lw, Tensor):
            raise TypeError(
                "state.particles and state.log_weights must be tensors, got "
                f"{type(x).__name__} and {type(lw).__name__}"
            )
        if x.dim() < 2 or x.shape[-1] != model.state_dim or tuple(x.shape[:-1]) != tuple(lw.shape):
            raise ValueError(
                f"state.particles must have shape (..., N, {model.state_dim}) and "
                f"state.log_weights (..., N) with the same leading dims, got "
                f"{tuple(x.shape)} and {tuple(lw.shape)}"
            )
        # (integer log-weights failed in torch.finfo, unnamed; float32 ones were promoted)
        if lw.dtype != x.dtype or lw.device != x.device:
            raise ValueError(
                f"state.log_weights must have the particles' dtype and device ({x.dtype}, "
                f"{x.device}), got {lw.dtype}, {lw.device}"
            )
        if (self.proposal is None) != (state.proposal is None):
            raise ValueError(
                "state.proposal must be a FilterState for a Gaussian-proposal filter and None "
                "for the bootstrap filter (build the state with this filter's init)"
            )
        if state.proposal is not None:
            # (another particle count failed in the engine's step, unnamed)
            chol = getattr(getattr(state.proposal, "belief", None), "chol", None)
            want = (*x.shape, x.shape[-1])
            if not isinstance(chol, Tensor) or tuple(chol.shape) != want:
                got = tuple(chol.shape) if isinstance(chol, Tensor) else type(chol).__name__
                raise ValueError(
                    f"state.proposal.belief.chol must have shape {want} (a factor per particle "
                    f"of state.particles {tuple(x.shape)}), got {got}"
                )
        _check_log_weights(lw)

    # ------------------------------------------------------------------ stages
    def _setup(self, model, bs: torch.Size, like: Tensor, k: int) -> _Setup:
        """Checks and views shared by the steps of a run (noise: only when constant), for the
        particles ``like`` ``(..., N, n)``: a resumed state's count ``N`` may differ from
        ``num_particles`` (which :meth:`init` draws); per-run noise was expanded to the
        latter and failed in ``expand``, unnamed."""
        gauss = self.proposal is not None
        const = _constant_noise(model)
        N = like.shape[-2]
        noise = _noise(model, k, bs, like, gauss) if const else None
        pmodel = _particle_model(model, len(bs), N) if gauss else None
        engine_noise = None
        if gauss and const:
            engine_noise = pmodel.checked_noise(k, (*bs, N), like)
        dev = like.device
        return _Setup(
            noise,
            pmodel,
            engine_noise,
            torch.zeros(bs, dtype=torch.bool, device=dev),
            torch.ones(bs, dtype=torch.bool, device=dev),
            torch.zeros(bs, dtype=torch.long, device=dev),
            torch.ones(bs, dtype=like.dtype, device=dev),
        )

    @staticmethod
    def _draw(pn: _PNoise, eps: Tensor) -> Tensor:
        """``S_Q eps`` for ``eps`` ``(..., N, n)``."""
        return eps * pn.dQ if pn.dQ is not None else eps @ pn.noise.chol_Q.mT

    def _transition_sample(self, model, x_prev, u_p, k, pn: _PNoise, eps):
        """``f(x_{k-1}) + q`` and a draw ``f(x_{k-1}) + q + S_Q eps`` (paper 002 Eq. 15)."""
        fq = model.transition(x_prev, u_p, k)
        if pn.q is not None:
            fq = fq + pn.q
        return fq, None if eps is None else fq + self._draw(pn, eps)

    def _log_lik(self, model, x, y, u_p, k, pn: _PNoise, observed=None) -> Tensor:
        """``log p(y_k | x_k^i)`` ``(..., N)`` (paper 002 Eq. 16); with ``observed`` ``(..., m)``
        (some run's vector partly missing; ``y`` 0 there) the density of each run's observed
        components, ``log p(y_{k,o} | x_k^i)``."""
        hx = model.observe(x, u_p, k)
        if pn.r is not None:
            hx = hx + pn.r
        e = (y if y.dim() == 1 else y.unsqueeze(-2)) - hx  # (one run: y broadcasts as it is)
        ll = _gauss_logpdf(e, pn.noise.chol_R, pn.kR, pn.inv_dR)
        if observed is None:
            return ll
        part = _observed_logpdf(e, pn.noise.chol_R, observed)
        return torch.where(observed.all(-1).unsqueeze(-1), ll, part)

    def predict(
        self,
        model: StateSpaceModel,
        state: ParticleState,
        u: Tensor | None = None,
        k: int = 1,
        *,
        generator: torch.Generator,
    ) -> ParticleState:
        """Propagate the particles through ``p(x_k | x_{k-1})``; weights unchanged (multi-step
        prediction, paper 002 "LS-SVR STPF method for failure prognosis", step 2).

        With a Gaussian proposal (EKPF, UPF, STPF) each particle's carried Gaussian is predicted
        by the engine as well (its factor grows by the transition and ``Q``), as in a
        :meth:`step` whose measurement is missing: the two give the same particles and Gaussians,
        bit for bit (the step renormalises the unchanged weights, to rounding).
        """
        self._check_state(model, state)
        x_prev = state.particles
        check_generator(generator, x_prev)
        bs = state.batch_shape
        u = check_control(u, model.control_dim, bs, x_prev)
        u_p = None if u is None else u if u.dim() == 1 else u.unsqueeze(-2)
        if state.proposal is None:
            pn = _noise(model, k, bs, x_prev)
            eps = standard_normal(x_prev.shape, generator, x_prev.dtype, x_prev.device)
            _, x = self._transition_sample(model, x_prev, u_p, k, pn, eps)
            return ParticleState(x, state.log_weights, None)
        setup = self._setup(model, bs, x_prev, k)
        pn = setup.noise if setup.noise is not None else _noise(model, k, bs, x_prev, True)
        eps = standard_normal(x_prev.shape, generator, x_prev.dtype, x_prev.device)
        y = torch.full((*bs, model.obs_dim), math.nan, dtype=x_prev.dtype, device=x_prev.device)
        args = (setup, model, state, y, torch.zeros_like(y), u, u_p, k, pn, eps, setup.yes_flag,
                True)  # fmt: skip
        x, _, fs, _, _, eng, checks = self._propose_gaussian(*args)
        if checks and not all_finite(torch.cat(checks)):  # test each Gaussian, as a step does
            x, _, fs, _, _, _, _ = self._propose_gaussian(*args, eng)
        return ParticleState(x, state.log_weights, fs)

    def _propose_gaussian(
        self, setup, model, state, y, y_safe, u, u_p, k, pn, eps, missing, any_missing, eng=None,
        observed=None,
    ):  # fmt: skip
        """Per-particle Gaussian proposal (paper 002 STPF steps 2-3; Van der Merwe et al. 2000).

        Returns the new particles, the log-weight increments
        ``log p(y|x) + log p(x|x_prev) - log q(x|x_prev, y)``, the carried filter state, the
        number of prior-fallback particles per run, the particles' fading factors, the engine's
        output ``eng`` and ``checks``. Without ``eng`` the engine step is run and every proposal
        is taken to be valid; ``checks`` (proposal means, factors and log-diagonals, or ``[]``
        when nothing is missing: the increments' finite test covers them) then go into the
        caller's one finite test, and where it fails the caller calls again with ``eng``, which
        tests each proposal and falls back where needed (``checks`` ``None``).
        """
        x_prev, fs = state.particles, state.proposal
        bs, N, n = state.batch_shape, state.num_particles, model.state_dim
        dt, dev = x_prev.dtype, x_prev.device
        prop = self.proposal
        assume = eng is None
        if eng is None:
            y_e = y.unsqueeze(-2).expand(*bs, N, model.obs_dim)
            u_e = None if u is None else u if u.dim() == 1 else u_p.expand(*bs, N, u.shape[-1])
            # the per-particle Gaussian is centred on the particle (Van der Merwe et al., Sec. 4)
            fs_in = fs
            if fs.belief.mean is not x_prev:
                fs_in = replace(fs, belief=GaussianBelief(x_prev, fs.belief.chol))
            try:
                # ONE engine step (Eq. 27), on inputs the particle filter has checked
                fs_step, pinfo = prop._update(
                    setup.pmodel, fs_in, y_e, u_e, k, any_missing, setup.engine_noise
                )
                lam_i = pinfo.fading_factor
                # the engine's prior mean is exactly f(x_prev) + q for the Taylor rule (fading
                # scales only the covariance) and the random walk; reuse it instead of calling f
                exact = (model.f is None or isinstance(prop.rule, Taylor)) and prop.noise is None
                eng = (fs_in, fs_step, lam_i, pinfo.prior.mean if exact else None, False)
            except torch.linalg.LinAlgError:
                lam_i = torch.ones((*bs, N), dtype=dt, device=dev)
                eng = (fs_in, fs_in, lam_i, None, True)
                assume = False
        fs_in, fs_step, lam_i, fq, failed = eng
        mu, L = fs_step.belief.mean, fs_step.belief.chol
        diag = torch.diagonal(L, dim1=-2, dim2=-1)
        if failed:
            ok, all_ok = torch.zeros((*bs, N), dtype=torch.bool, device=dev), False
            mu = x_prev
        elif assume:
            ok, all_ok = None, True
        else:
            ok = torch.isfinite(mu).all(-1) & torch.isfinite(L).all(-1).all(-1) & (diag > 0).all(-1)
            all_ok = bool(ok.all())
        # (when every proposal is finite, so is fq: mu = fq + K e would not be finite otherwise)
        if fq is None or (not all_ok and not bool(torch.isfinite(fq).all())):
            fq, _ = self._transition_sample(model, x_prev, u_p, k, pn, None)
        # sample from the proposal N(mu, L L^T) (Eq. 27); its log density uses eps directly
        if n == 1:
            x_q = mu + L[..., 0] * eps
        else:
            x_q = mu + (L @ eps.unsqueeze(-1)).squeeze(-1)
        log_diag = torch.log(diag)
        log_q = -0.5 * (n * _LOG_2PI + _sum_last(eps * eps)) - _sum_last(log_diag)
        fast = all_ok and not any_missing
        if fast:
            x = x_q
        else:  # draw from p(x_k | x_{k-1}) where the proposal is invalid or y is missing
            if ok is None:
                ok = torch.ones((*bs, N), dtype=torch.bool, device=dev)
            use_q = ok & ~missing[..., None]
            x = torch.where(use_q[..., None], x_q, fq + self._draw(pn, eps))
        log_lik = self._log_lik(model, x, y_safe, u_p, k, pn, observed)
        log_trans = _gauss_logpdf(x - fq, pn.noise.chol_Q, pn.kQ, pn.inv_dQ)
        inc = log_lik + log_trans - log_q  # STPF step 3 (in log space)
        n_bad = None
        if not fast:
            inc = torch.where(use_q, inc, log_lik)
            n_bad = (~ok & ~missing[..., None]).sum(-1)
        if not all_ok:
            if bool((n_bad > 0).any()):
                warnings.warn(
                    f"step {k}: {int(n_bad.sum())} particle proposals were not finite/positive "
                    "definite; those particles were drawn from the transition prior",
                    ProposalFallbackWarning,
                    stacklevel=4,
                )
            fs_step = where_particles(ok, fs_step, fs_in)
        fs_new = replace(fs_step, belief=GaussianBelief(x, fs_step.belief.chol))
        # checks for the caller's one finite test (None: each proposal was tested). Without
        # missing runs none are needed: x = mu + L eps with a finite eps is finite only if mu and
        # L are, and a finite increment has a finite log q, i.e. finite log-diagonals of L (so a
        # positive diagonal), and a finite log p(x | x_prev), so a finite x
        checks = None
        if assume:
            checks = [mu.reshape(-1), L.reshape(-1), log_diag.reshape(-1)] if not fast else []
        return x, inc, fs_new, n_bad, lam_i, eng, checks

    def _ancestors(self, lw: Tensor, W: Tensor, generator: torch.Generator) -> Tensor:
        """Ancestor indices ``(..., N)`` of valid normalised log-weights ``lw`` with
        ``W = exp(lw)`` (no re-validation). The inverse-CDF schemes normalise their cumulative
        sum themselves and take ``W``; residual resampling needs ``N w_i`` exactly normalised
        and takes ``softmax(lw)``."""
        if callable(self.resampler):
            anc = self.resampler(lw, generator)
            # (before the runs that do not resample are merged in, which would broadcast)
            if not isinstance(anc, Tensor) or tuple(anc.shape) != tuple(lw.shape):
                got = tuple(anc.shape) if isinstance(anc, Tensor) else type(anc).__name__
                raise ValueError(
                    f"the resampler must return ancestors of shape {tuple(lw.shape)}, got {got}"
                )
            # (a float index failed in gather or index_select, unnamed; an index outside
            # 0..N-1 there too, and on a GPU as a device-side assert)
            if anc.is_floating_point() or anc.is_complex() or anc.dtype == torch.bool:
                raise TypeError(
                    f"the resampler must return integer ancestors (int64), got {anc.dtype}"
                )
            if anc.device != lw.device:
                raise ValueError(
                    f"the resampler must return ancestors on the weights' device {lw.device}, "
                    f"got {anc.device}"
                )
            anc = anc.long()
            _check_ancestors(anc, "the resampler's ancestors")
            return anc
        name = self.resampler.lower()
        w = torch.softmax(lw, dim=-1) if name == "residual" else W
        return _draw_ancestors(name, w, generator)

    def step(
        self,
        model: StateSpaceModel,
        state: ParticleState,
        y: Tensor,
        u: Tensor | None = None,
        k: int = 1,
        *,
        generator: torch.Generator,
    ) -> tuple[ParticleState, ParticleStepInfo]:
        """One propagate / reweight / estimate / resample step (paper 002 STPF steps 2-6).

        Args:
            model: the state-space model (additive Gaussian noise; per-step noise honoured).
            state: :class:`ParticleState` at ``k - 1``.
            y: ``(..., m)`` measurement of each run (NaN: missing; a run whose vector is NaN
                throughout propagates only, a partly NaN one is weighted by the density of its
                observed components, with which a Gaussian proposal updates).
            u: control ``(p,)`` or ``(..., p)``, or ``None``.
            k: step index passed to ``f``, ``h`` and the noise callables.
            generator: ``torch.Generator`` on the particles' device.
        Returns:
            The new (possibly resampled) state and a :class:`ParticleStepInfo`.
        """
        self._check_state(model, state)
        x_prev = state.particles
        check_generator(generator, x_prev)
        bs = state.batch_shape
        y, any_nan = check_measurement(y, model.obs_dim, bs, x_prev, owner="particles")
        u = check_control(u, model.control_dim, bs, x_prev)
        setup = self._setup(model, bs, x_prev, k)
        missing = observed = None
        if any_nan:
            nan = torch.isnan(y)
            missing = nan.all(-1)
            if bool((nan.any(-1) & ~missing).any()):
                observed = ~nan
        return self._step(model, setup, state, y, u, k, generator, missing, observed)

    def _step(
        self,
        model: StateSpaceModel,
        setup: _Setup,
        state: ParticleState,
        y: Tensor,
        u: Tensor | None,
        k: int,
        generator: torch.Generator,
        missing: Tensor | None,
        observed: Tensor | None = None,
    ) -> tuple[ParticleState, ParticleStepInfo]:
        """:meth:`step` on checked inputs: ``y`` in the particles' dtype, ``u`` checked,
        ``missing`` ``(...)`` bool, the runs whose ``y`` is NaN throughout, where some entry of
        ``y`` is NaN (else ``None``); ``observed`` ``(...)`` ``~isnan(y)`` where some run's
        vector is partly missing (else ``None``): those runs are weighted by the density of
        their observed components, and a Gaussian proposal updates with them."""
        x_prev, lw_prev = state.particles, state.log_weights
        bs, N = state.batch_shape, state.num_particles
        dt, dev = x_prev.dtype, x_prev.device
        u_p = None if u is None else u if u.dim() == 1 else u.unsqueeze(-2)
        any_missing = missing is not None
        if any_missing:
            y_safe = torch.where(torch.isnan(y), torch.zeros_like(y), y)
        else:
            missing = setup.no_flag
            y_safe = y
        pn = setup.noise
        if pn is None:
            pn = _noise(model, k, bs, x_prev, self.proposal is not None)

        eps = standard_normal(x_prev.shape, generator, dt, dev)
        checks: list[Tensor] | None = None
        if self.proposal is None:
            fallback = None
            fs_new = None
            _, x = self._transition_sample(model, x_prev, u_p, k, pn, eps)
            inc = self._log_lik(model, x, y_safe, u_p, k, pn, observed)
            lam_prop = None
        else:
            args = (setup, model, state, y, y_safe, u, u_p, k, pn, eps, missing, any_missing)
            x, inc, fs_new, fallback, lam_prop, eng, checks = self._propose_gaussian(
                *args, observed=observed
            )

        # missing runs: propagate only, weights unchanged
        if any_missing:
            inc = torch.where(missing[..., None], torch.zeros_like(inc), inc)
        lw_un = lw_prev + inc
        ll = _log_normaliser(lw_un)  # (infinite maxima give NaN and take the exact path)
        # one host read: particles, increments, fading factors and the likelihood all finite
        # (a finite sum has finite terms; an overflowing one takes the exact path below)
        if lam_prop is None:
            # a NaN or +inf increment makes the likelihood NaN; a -inf one (a particle the
            # measurement rules out) is handled by the fast path as by the exact one
            total = x.sum() + (ll if ll.dim() == 0 else ll.sum())
        else:
            if checks == []:  # (x is covered by inc, see _propose_gaussian)
                parts = [inc, ll, lam_prop]
            else:
                parts = [x, inc, ll, lam_prop, *(checks or ())]
            if x.numel() < _SUM_PARTS_MIN:  # one concatenation and one sum
                total = torch.cat([t if t.dim() == 1 else t.reshape(-1) for t in parts]).sum()
            else:  # the sum of each part (a concatenation would copy them)
                total = torch.stack([t.sum() for t in parts]).sum()
        finite = math.isfinite(_host_float(total))
        collapsed = None
        if not finite and self.proposal is not None and checks is not None:
            # some proposal may be invalid: test each one, with fallbacks (same engine step)
            x, inc, fs_new, fallback, lam_prop, eng, checks = self._propose_gaussian(
                *args, eng, observed=observed
            )
            if any_missing:
                inc = torch.where(missing[..., None], torch.zeros_like(inc), inc)
        if not finite:
            finite_x = torch.isfinite(x).all(-1)
            inc = torch.where(torch.isfinite(inc) & finite_x, inc, torch.full_like(inc, -math.inf))
            lw_un = lw_prev + inc
            ll = torch.logsumexp(lw_un, -1)
            collapsed = ~torch.isfinite(ll)
            if bool(collapsed.any()):
                if bool((collapsed & ~finite_x.any(-1)).any()):
                    raise FloatingPointError(
                        f"step {k}: every particle of a run is non-finite (check f, h and the "
                        "noise)"
                    )
                warnings.warn(
                    f"step {k}: particle weights collapsed (all zero or non-finite) in "
                    f"{int(collapsed.sum())} of {collapsed.numel()} runs; weights reset to uniform",
                    WeightCollapseWarning,
                    stacklevel=3,
                )
                reset = torch.where(
                    finite_x, torch.zeros_like(lw_un), torch.full_like(lw_un, -math.inf)
                )
                lw_un = torch.where(collapsed[..., None], reset, lw_un)
                ll = torch.where(collapsed, torch.full_like(ll, -math.inf), ll)
                lw = lw_un - torch.logsumexp(lw_un, -1, keepdim=True)
            else:
                lw = lw_un - ll.unsqueeze(-1)
        else:  # STPF step 4 (ll is logsumexp(lw_un))
            lw = lw_un - (ll if ll.dim() == 0 else ll.unsqueeze(-1))

        # estimates (STPF step 5); zero-weight particles may be non-finite: mask them
        W = lw.exp()
        xs = x if finite else torch.where((W > 0)[..., None], x, torch.zeros_like(x))
        mean, cov, n_eff = _estimates(W, xs)
        if lam_prop is None:
            lam = setup.unit
        elif finite:
            lam = (W * lam_prop).sum(-1)
        else:
            lam = (
                W * torch.where(torch.isfinite(lam_prop), lam_prop, torch.ones_like(lam_prop))
            ).sum(-1)

        x_w, lw_w = x, lw
        # resampling (STPF step 6): particles, weights and every per-particle Gaussian
        thr = self.resample_threshold
        if n_eff.dim() == 0:  # one run: one host read, no comparison and count on tensors
            n_do = int(_host_float(n_eff) < thr * N)
            if n_do and thr > _UNIFORM_CHECK:  # (uniform weights are kept: N_eff = N rounded)
                n_do = int(bool(lw.amax() > lw.amin()))
            do = setup.yes_flag if n_do else setup.no_flag
        else:
            do = _resample_flags(n_eff, lw, thr)
            n_do = int(do.sum())
        if n_do:
            anc = self._ancestors(lw, W, generator)
            if n_do < do.numel():
                anc, lw = _resample_some(do, anc, lw)
            else:
                lw = torch.full_like(lw, -math.log(N))
            if fs_new is not None:  # its belief's mean is x: gathered with it
                fs_new = _gather(fs_new, anc)
                x = fs_new.belief.mean
            elif anc.dim() == 1:
                x = x.index_select(0, anc)
            else:
                x = torch.gather(x, -2, anc.unsqueeze(-1).expand(x.shape))

        if any_missing:
            ll = torch.where(missing, torch.zeros_like(ll), ll)
        info = ParticleStepInfo(
            mean=mean,
            cov=cov,
            ess=n_eff,
            resampled=do,
            log_likelihood=ll,
            collapsed=setup.no_flag if collapsed is None else collapsed,
            prior_fallback=setup.no_count if fallback is None else fallback,
            fading_factor=lam,
            missing=missing,
            particles=x_w,
            log_weights=lw_w,
        )
        return ParticleState(x, lw, fs_new), info

    # ------------------------------------------------------------------ run
    def run(
        self,
        model: StateSpaceModel,
        init: GaussianBelief | ParticleState,
        ys: Tensor,
        us: Tensor | None = None,
        *,
        generator: torch.Generator,
        k0: int = 0,
        keep_particles: bool = False,
        inference: bool = False,
        compile: bool = False,
    ) -> ParticleTrajectory:
        """Filter the measurements ``ys`` ``(T, ..., m)`` (NaN rows: missing).

        Step ``t`` (0-based) uses ``k = k0 + t + 1``, ``us[t]`` (``(T, ..., p)`` or ``(T, p)``)
        and ``ys[t]``. ``init`` is the belief on ``x_{k0}`` (particles are drawn from it) or a
        :class:`ParticleState` to resume. With ``keep_particles`` the weighted particle sets
        (before resampling) are returned as well.

        The inputs are checked once for the whole sequence (shapes, devices, finiteness, the
        noise when it is constant); each step is then :meth:`step` without the checks.

        The runs of a batch share ``generator``: resampling draws are taken at the steps where
        any run resamples, so one run's draws, and its estimates within their Monte Carlo
        error, change with the other runs' data (the Gaussian filters' runs are independent);
        filter a run alone where its numbers must not depend on its batch.

        ``inference=True`` runs the steps after the first under ``torch.inference_mode()``
        (:func:`~prognos_torch.filters.scan`; the same numbers, about 15 % less time for a
        batched STPF of 1,000 particles) unless the first step's outputs need a gradient. Only
        for models that do not differentiate inside ``f``, ``h`` or their Jacobians and runs
        outside forward-mode AD: ``torch.autograd.functional.jacobian`` returns zeros in
        inference mode, and a parameter that the first step does not use would lose its
        gradient. The results are ordinary tensors either way.

        ``compile=True`` runs the bootstrap filter, the EKPF or the STPF (an EKF proposal
        without noise estimator or robust bound, with the model's closed-form ``jac_f`` and
        ``jac_h``), with systematic resampling, constant model noise, complete ``ys`` and no
        input requiring a gradient (otherwise a ``ValueError`` names what is missing), as ONE
        ``torch.compile(fullgraph=True)`` call (:mod:`prognos_torch.filters._particle_compiled`):
        every step's uniforms drawn before the pass, the normals made inside it, the resampling
        decision a tensor. Its random stream differs from the eager run's (fed the same draws,
        the two agree to rounding). ``f``, ``h`` and the Jacobians get ``k=None`` (they must
        not depend on the step index) and are traced once. The first call for a configuration
        compiles (seconds; the time is ``prognos_torch.filters.sequence.last_compile_seconds``),
        later ones with an equal filter, the same model and the same shapes reuse the code. A
        pass that is not all finite (the eager step's exact path) is discarded and the run is
        redone eagerly from the same generator state. Pays from about 10^3 particles; the
        results carry no gradient.
        """
        if not isinstance(compile, bool):
            raise TypeError(f"compile must be a bool, got {type(compile).__name__}")
        if compile:  # (before any draw: an error leaves the generator as it was)
            check_compilable(self, model, ys, us, init)
        check_nonneg_int(k0, "k0")  # (a float k0 reached f, h and the noise as k)
        saved = (
            generator.get_state() if compile and isinstance(generator, torch.Generator) else None
        )
        if isinstance(init, ParticleState):
            state = init
            self._check_state(model, state)
        else:
            state = self.init(model, init, generator=generator, k=k0)
        like = state.particles
        check_generator(generator, like)
        bs = state.batch_shape
        check_sequence(ys, "ys", model.obs_dim, bs, nonempty=True)
        if ys.device != like.device:
            raise ValueError(f"ys is on {ys.device}, the particles on {like.device}")
        ys = ys.to(like.dtype)
        T = ys.shape[0]
        miss_rows: list[bool] = [False] * T  # steps with a NaN entry
        part_rows: list[bool] = [False] * T  # steps where some run's vector is partly NaN
        miss = observed = None
        if has_missing(ys, "ys", "measurement"):
            nan = torch.isnan(ys)
            miss = nan.all(-1)  # (T, ...) runs with no component observed
            miss_rows = nan.reshape(T, -1).any(-1).tolist()
            part_rows = (nan.any(-1) & ~miss).reshape(T, -1).any(-1).tolist()
            observed = ~nan
        if model.control_dim:
            check_sequence(us, "us", model.control_dim, bs, steps=T, shared=True)
            if us.device != like.device:
                raise ValueError(f"us is on {us.device}, the particles on {like.device}")
            if not all_finite(us):
                raise ValueError("us contains non-finite values")
            us = us.to(like.dtype)
        elif us is not None:
            raise ValueError("us was given but the model has control_dim=0")
        setup = self._setup(model, bs, like, k0 + 1)
        if compile:
            out = compiled_run(self, model, state, ys, us, setup, generator, keep_particles)
            if out is not None:
                return ParticleTrajectory(**out["rows"], final=ParticleState(*out["final"]))
            generator.set_state(saved)  # type: ignore[union-attr]  # not all finite: redo eagerly
            return self.run(
                model,
                init,
                ys,
                us,
                generator=generator,
                k0=k0,
                keep_particles=keep_particles,
                inference=inference,
            )

        def step(s: ParticleState, y: Tensor, u: Tensor | None, k: int):
            t = k - k0 - 1
            missing = miss[t] if miss_rows[t] else None  # type: ignore[index]
            obs = observed[t] if part_rows[t] else None  # type: ignore[index]
            return self._step(model, setup, s, y, u, k, generator, missing, obs)

        def record(s: ParticleState, info: ParticleStepInfo) -> dict[str, Tensor | None]:
            return {
                "means": info.mean,
                "covs": info.cov,
                "ess": info.ess,
                "resampled": info.resampled,
                "log_likelihoods": info.log_likelihood,
                "collapsed": info.collapsed,
                "prior_fallback": info.prior_fallback,
                "fading_factors": info.fading_factor,
                "missing": info.missing,
                "particles": info.particles if keep_particles else None,
                "log_weights": info.log_weights if keep_particles else None,
            }

        def rewind():  # a step redone with autograd draws the same numbers again
            saved = generator.get_state()
            return lambda: generator.set_state(saved)

        state, stacked = scan(
            step, state, ys, us, record=record, k0=k0, inference=inference, rewind=rewind
        )
        return ParticleTrajectory(**stacked, final=state)
