"""The compiled pass of the particle filters: ``ParticleFilter.run(..., compile=True)`` (private
to :mod:`prognos_torch.filters.particle`).

The run is ONE ``torch.compile(fullgraph=True)`` call: :func:`~prognos_torch.filters.scan` with
``compile=True`` (the step traced once, the loop torch's scan operator) over a step made of the
eager step's blocks: for the bootstrap filter the transition draw and the log-likelihood of
:class:`~prognos_torch.filters.particle.ParticleFilter` (paper 002 Eq. 15-16), for the EKPF and
the STPF its per-particle proposal (one engine step per particle, Eq. 27, with the engine's
fallbacks deferred as in the optimiser's compiled pass), then the log-normaliser and estimates
(STPF steps 4-5) and systematic resampling by offspring counts of the particles and everything
they carry (step 6, :mod:`~prognos_torch.filters.resampling`). Where torch's scan operator
refuses the traced step (it takes no inputs that alias each other, which a model's closures can
give it: ``A`` in ``h`` and ``A.mT`` in ``f``), the pass is the eager
:func:`~prognos_torch.filters.scan` over the step compiled alone, one compiled call per step.
What moves against the eager filter is where the randomness and the decisions live:

- Every step's uniforms are drawn before the pass, in one ``torch.rand`` call. Step ``t`` takes
  ``16 ceil(B N n / 16)`` of them for its normals (``B`` runs, ``N`` particles, ``n`` states),
  turned into normals inside the step by torch's Box-Muller transform in blocks of 16
  (:func:`~prognos_torch.core.random.box_muller`), then one per run for the systematic
  resampling point. The random stream therefore differs from the eager run's, which draws per
  step and a resampling point only when it resamples. Fed the same normals and points, the two
  agree to rounding (``tests/test_particle_compiled.py``, 1e-12).
- The resampling decision stays a tensor: ``torch.cond`` resamples when some run's ``N_eff``
  falls below the threshold, and ``torch.where`` keeps the runs that do not.
- Nothing is read on the host during the pass, and every proposal is taken to be valid. A pass
  whose log-likelihoods, estimates, fading factors, particles or proposal factors are not all
  finite (what the eager step's exact path handles: every particle of a run ruled out, weight
  collapse, non-finite particles, invalid proposals) is discarded, and the run is redone
  eagerly from the same generator state.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace

import torch
from torch import Tensor

from ..adapt.strong_tracking import StrongTrackingState
from ..core.belief import GaussianBelief
from ..core.model import Noise
from ..core.random import box_muller
from ..core.validation import all_finite
from ._blocks import FilterState, Taylor
from ._particle_blocks import (
    ParticleState,
    _estimates,
    _log_normaliser,
    _resample_flags,
    _resample_some,
)
from ._particle_noise import _constant_noise, _Setup
from ._particle_trees import _gather
from .gaussian import deferred_fallbacks
from .resampling import _arange, _cdf, _systematic_by_counts
from .sequence import _compile_options, _compiled_scan, scan

__all__ = ["check_compilable", "compiled_run"]

#: the step and record functions of recent compiled runs, reused so that a later run with the
#: same filter, model, noise and shapes reuses the compiled code (the scan's cache is keyed on
#: the functions)
_STEPS: dict = {}


def check_compilable(pf, model, ys: Tensor, us: Tensor | None, init) -> None:
    """Raise a ``ValueError`` naming what ``run(..., compile=True)`` needs that the filter, the
    model or the data lack."""
    why = None
    prop = pf.proposal
    if prop is not None and (
        not isinstance(prop.rule, Taylor)
        or not prop.sqrt
        or prop.noise is not None
        or prop.robust is not None
    ):
        why = (
            "the bootstrap filter (sir()) or a square-root EKF proposal without noise estimator "
            "or robust bound (ekpf(), stpf())"
        )
    elif prop is not None and (
        model.jac_h is None or (model.f is not None and model.jac_f is None)
    ):
        why = "closed-form Jacobians (the model's jac_f and jac_h) for an EKF proposal"
    elif not isinstance(pf.resampler, str) or pf.resampler.lower() != "systematic":
        why = 'resampler="systematic"'
    elif not _constant_noise(model):
        why = "a model whose noise (q, chol_Q, r, chol_R) is constant, not a function of k"
    if why is not None:
        raise ValueError(f"run(compile=True) needs {why}; use compile=False")
    if isinstance(ys, Tensor) and bool(torch.isnan(ys).any()):
        raise ValueError(
            "ys contains NaN (missing measurements): the compiled pass needs complete "
            "measurements; compile=False propagates over the missing ones"
        )
    leaves = [ys, us]
    for name in ("mean", "chol", "particles", "log_weights"):
        leaves.append(getattr(init, name, None))
    if torch.is_grad_enabled() and any(isinstance(t, Tensor) and t.requires_grad for t in leaves):
        raise ValueError(
            "run(compile=True) records no gradient, and an input requires one; use compile=False"
        )


def _carried(fs: FilterState | None) -> tuple[Tensor, ...]:
    """The tensors a particle carries besides itself: its proposal Gaussian's square root and,
    with strong tracking, its ``V_k`` and start flag."""
    if fs is None:
        return ()
    out = (fs.belief.chol.contiguous(),)
    if fs.fading is not None:
        out += (fs.fading.V.contiguous(), fs.fading.started.contiguous())
    return out


def _proposal_state(x: Tensor, extra: tuple) -> FilterState | None:
    """The inverse of :func:`_carried` (the Gaussian's mean is the particle)."""
    if not extra:
        return None
    fading = StrongTrackingState(extra[1], extra[2]) if len(extra) == 3 else None
    return FilterState(GaussianBelief(x, extra[0]), fading)


def _copies(noise: Noise) -> Noise:
    """``noise`` with every tensor copied (its own storage)."""
    return Noise(
        *(
            v.clone() if isinstance(v, Tensor) else v
            for v in (getattr(noise, f.name) for f in fields(noise))
        )
    )


def compiled_run(
    pf, model, state, ys: Tensor, us: Tensor | None, setup: _Setup,
    generator: torch.Generator, keep_particles: bool,
) -> dict | None:  # fmt: skip
    """The records of :meth:`ParticleFilter.run` (``means``, ``covs``, ...) and the final
    particles, log-weights and proposal state (``final``) from one compiled pass over checked
    inputs (``ys`` ``(T, ..., m)`` in the particles' dtype, ``us`` ``(T, p)``/``(T, ..., p)``
    or ``None``, ``setup`` the run's, with its constant noise), or ``None`` when the pass was
    not all finite (the caller then runs eagerly). The compile time of a whole-pass scan is
    :data:`prognos_torch.filters.sequence.last_compile_seconds` (a pass compiled step by step
    compiles inside its first step)."""
    x0, lw0 = state.particles, state.log_weights
    bs, N, n = state.batch_shape, state.num_particles, x0.shape[-1]
    T, dt, dev = ys.shape[0], x0.dtype, x0.device
    count = x0.numel()
    M = 16 * -(-count // 16)  # uniforms for the normals, whole blocks of 16
    R = math.prod(bs)  # one resampling point per run
    P = 0 if us is None else math.prod(us.shape[1:])
    # every step's uniforms, drawn on the generator's device in one call (see the docstring)
    draws = torch.rand((T, M + R), generator=generator, dtype=dt, device=generator.device)
    packed = draws.to(dev) if us is None else torch.cat([us.reshape(T, P), draws.to(dev)], 1)
    u_shape = None if us is None else tuple(us.shape[1:])
    extra = _carried(state.proposal)
    if setup.engine_noise is not None:
        # the engine's noise with the particle dim is a view of the particle side's: copies,
        # since the scan takes no inputs that alias each other
        setup = replace(setup, engine_noise=_copies(setup.engine_noise))
    step, record = _step_functions(
        pf, model, setup, tuple(bs), N, n, u_shape, M, len(extra), keep_particles
    )
    if bs:  # the histogram offsets of the batched counts, cached outside the trace
        _arange(R, torch.int64, dev)
    carry = (x0.contiguous(), lw0.contiguous(), *extra)
    with torch.no_grad(), deferred_fallbacks():
        final, rows = _scan_compiled(step, carry, ys, packed, record)
    names = ("log_likelihoods", "means", "covs", "fading_factors")
    if not (all(all_finite(rows[k]) for k in names if k in rows) and all_finite(final[0])):
        return None
    if len(final) > 2 and not all_finite(final[2]):
        return None
    flags = torch.zeros((T, *bs), dtype=torch.bool, device=dev)
    rows.update(
        collapsed=flags,
        missing=flags.clone(),
        prior_fallback=torch.zeros((T, *bs), dtype=torch.long, device=dev),
    )
    rows.setdefault("fading_factors", torch.ones((T, *bs), dtype=dt, device=dev))
    rows.setdefault("particles", None)
    rows.setdefault("log_weights", None)
    x, lw = final[0], final[1]
    return {"rows": rows, "final": (x, lw, _proposal_state(x, tuple(final[2:])))}


#: inductor's C++ wrapper for the whole-pass scan on the CPU. Off: in torch 2.13 it passes a
#: loop input that is a view with its base's own layout (``F.mT`` of a model's 1 x 1 ``F``,
#: ``x @ F.mT`` in a one-state linear model: the attribute is evaluated outside the loop) as a
#: temporary handle that the first iteration frees, and the process aborts. A model's closures
#: are not visible to a check, so the whole-pass scan takes the Python wrapper always (the
#: step compiled alone, where the scan operator refuses it, has no loop and keeps the C++ one).
CPP_WRAPPER = False

#: steps whose whole-pass trace failed (they run as one compiled call per step)
_PER_STEP: dict = {}


def _scan_compiled(step, carry: tuple, ys: Tensor, packed: Tensor, record):
    """The pass as one compiled scan (static shapes: each new ``(T, N, ...)`` compiles on its
    own, see ``_compiled_scan``) or, where torch's scan operator cannot take the step, the
    library's :func:`~prognos_torch.filters.scan` over the step compiled alone (one compiled
    call per step, about 60 us each on the CPU). The scan operator refuses inputs that alias
    each other, which a model's closures can give it (a matrix and its transpose, ``A`` in
    ``h`` and ``A.mT`` in ``f``). A step that torch cannot compile at all (a model that reads
    a tensor on the host, branches on its values, or uses ``k``) is a ``RuntimeError`` that
    says so."""
    dynamo = torch._dynamo.exc
    fn = _PER_STEP.get(step)
    try:
        if fn is None:
            try:
                return _compiled_scan(
                    step, carry, ys, packed, record, dynamic=False, cpp_wrapper=CPP_WRAPPER
                )
            except (dynamo.Unsupported, dynamo.UncapturedHigherOrderOpError):
                device = carry[0].device
                compiled = torch.compile(
                    step, fullgraph=True, dynamic=False, **_compile_options(device)
                )
                if len(_PER_STEP) > 16:
                    _PER_STEP.clear()
                # (k = None: a step index would be a new constant, and a compile, each step)
                fn = _PER_STEP[step] = lambda s, y, u, k: compiled(s, y, u, None)
        return scan(fn, carry, ys, packed, record=record)
    except dynamo.TorchDynamoException as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise RuntimeError(
            "run(compile=True) could not compile this filter's step with this model "
            f"({type(err).__name__}: {first}); f, h and their Jacobians must be traceable "
            "tensor code that does not use k; use compile=False"
        ) from err


def _step_functions(
    pf, model, setup: _Setup, bs: tuple, N: int, n: int, u_shape, M: int, n_extra: int,
    keep: bool,
):  # fmt: skip
    """The scan's step and record for this configuration (kept for reuse)."""
    pn = setup.noise
    # an equal filter configuration, the same model and its noise as given (the same tensors,
    # unmodified: the same checked noise)
    raw = (model, model.q, model.chol_Q, model.r, model.chol_R)
    versions = tuple(getattr(v, "_version", None) for v in raw[1:])
    try:
        cfg = hash(pf)
    except TypeError:  # (a configuration that does not hash: a callable resampler's state)
        cfg = id(pf)
    # (the noise is in the particles' dtype and on their device)
    key = (
        cfg,
        *map(id, raw),
        versions,
        bs,
        N,
        n,
        u_shape,
        n_extra,
        keep,
        pn.kR.dtype,
        pn.kR.device,
    )
    hit = _STEPS.get(key)
    if hit is not None and hit[0] == pf and all(a is b for a, b in zip(hit[1], raw)):
        return hit[2], hit[3]
    log_uniform = -math.log(N)
    P = 0 if u_shape is None else math.prod(u_shape)
    count = math.prod(bs) * N * n

    def resample(W: Tensor, U: Tensor, do: Tensor, x: Tensor, lw: Tensor, *extra: Tensor):
        # STPF step 6: systematic resampling of the runs whose N_eff fell below the threshold,
        # the particles with everything they carry
        anc = _systematic_by_counts(_cdf(W), U, traced=True)
        if bs:  # the other runs keep their particles
            anc, lw_r = _resample_some(do, anc, lw)
        else:  # (one run resamples: the cond chose this branch)
            lw_r = torch.full_like(lw, log_uniform)
        return (_gather(x, anc), lw_r, *(_gather(t, anc) for t in extra))

    def keep_all(W: Tensor, U: Tensor, do: Tensor, *carry: Tensor):
        return tuple(t.clone() for t in carry)

    def step(carry, y: Tensor, packed: Tensor, k):
        x_prev, lw_prev, *extra = carry
        u = None if P == 0 else packed[:P].reshape(u_shape)
        u_p = None if u is None else u if u.dim() == 1 else u.unsqueeze(-2)
        eps = box_muller(packed[P : P + M].reshape(-1, 16)).reshape(-1)[:count]
        eps = eps.reshape(x_prev.shape)
        U = packed[P + M :].reshape(*bs, 1)
        lam = None
        if pf.proposal is None:
            _, x = pf._transition_sample(model, x_prev, u_p, k, pn, eps)  # Eq. 15
            inc = pf._log_lik(model, x, y, u_p, k, pn)  # Eq. 16
        else:  # one engine step per particle (Eq. 27), every proposal taken as valid
            fs = _proposal_state(x_prev, tuple(extra))
            args = (setup, model, ParticleState(x_prev, lw_prev, fs), y, y, u, u_p, k, pn, eps)
            x, inc, fs_new, _, lam, _, _ = pf._propose_gaussian(*args, setup.no_flag, False)
            extra = list(_carried(fs_new))
        x = x.contiguous()  # (the two branches of the cond below must agree in layout)
        lw_un = lw_prev + inc
        ll = _log_normaliser(lw_un)
        lw = lw_un - ll.unsqueeze(-1)
        W = lw.exp()
        mean, cov, n_eff = _estimates(W, x)
        if lam is not None:
            lam = (W * lam).sum(-1)
        do = _resample_flags(n_eff, lw, pf.resample_threshold)
        new = torch.cond(do.any(), resample, keep_all, (W, U, do, x, lw, *extra))
        return tuple(new), (mean, cov, n_eff, do, ll, lam, x, lw)

    def record(s, info) -> dict[str, Tensor]:
        mean, cov, n_eff, do, ll, lam, x, lw = info
        row = {"means": mean, "covs": cov, "ess": n_eff, "resampled": do, "log_likelihoods": ll}
        if lam is not None:
            row["fading_factors"] = lam
        if keep:
            row.update(particles=x, log_weights=lw)
        return row

    if len(_STEPS) > 16:
        _STEPS.clear()
    _STEPS[key] = (pf, raw, step, record)
    return step, record
