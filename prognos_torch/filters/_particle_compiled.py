"""The compiled pass of the bootstrap particle filter: ``ParticleFilter.run(..., compile=True)``
(private to :mod:`prognos_torch.filters.particle`).

The run is ONE ``torch.compile(fullgraph=True)`` call: :func:`~prognos_torch.filters.scan` with
``compile=True`` (the step traced once, the loop torch's scan operator) over a step made of the
eager step's blocks: the transition draw and the log-likelihood of
:class:`~prognos_torch.filters.particle.ParticleFilter` (paper 002 Eq. 15-16), its log-normaliser
and estimates (STPF steps 4-5) and systematic resampling by offspring counts (step 6,
:mod:`~prognos_torch.filters.resampling`). What moves is where the randomness and the decisions
live:

- Every step's uniforms are drawn before the pass, in one ``torch.rand`` call. Step ``t`` takes
  ``16 ceil(B N n / 16)`` of them for its normals (``B`` runs, ``N`` particles, ``n`` states),
  turned into normals inside the step by torch's Box-Muller transform in blocks of 16
  (:func:`~prognos_torch.core.random.box_muller`), then one per run for the systematic
  resampling point. The random stream therefore differs from the eager run's, which draws per
  step and a resampling point only when it resamples. Fed the same normals and points, the two
  agree to rounding (``tests/test_particle_compiled.py``, 1e-12).
- The resampling decision stays a tensor: ``torch.cond`` resamples when some run's ``N_eff``
  falls below the threshold, and ``torch.where`` keeps the runs that do not.
- Nothing is read on the host during the pass. A pass whose log-likelihoods, estimates or
  particles are not all finite (what the eager step's exact path handles: every particle of a
  run ruled out, weight collapse, non-finite particles) is discarded, and the run is redone
  eagerly from the same generator state.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..core.random import box_muller
from ..core.validation import all_finite
from ._particle_blocks import _estimates, _log_normaliser
from ._particle_noise import _constant_noise, _PNoise
from .resampling import _arange, _cdf, _systematic_by_counts
from .sequence import _compiled_scan

__all__ = ["check_compilable", "compiled_run"]

#: the step and record functions of recent compiled runs, reused so that a later run with the
#: same filter, model, noise and shapes reuses the compiled code (the scan's cache is keyed on
#: the functions)
_STEPS: dict = {}


def check_compilable(pf, model, ys: Tensor, us: Tensor | None, init) -> None:
    """Raise a ``ValueError`` naming what ``run(..., compile=True)`` needs that the filter, the
    model or the data lack."""
    why = None
    if pf.proposal is not None:
        why = "the bootstrap filter (proposal=None, sir())"
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


def compiled_run(
    pf,
    model,
    state,
    ys: Tensor,
    us: Tensor | None,
    pn: _PNoise,
    generator: torch.Generator,
    keep_particles: bool,
) -> dict | None:
    """The records of :meth:`ParticleFilter.run` (``means``, ``covs``, ..., and ``final``) from
    one compiled pass over checked inputs (``ys`` ``(T, ..., m)`` in the particles' dtype,
    ``us`` ``(T, p)``/``(T, ..., p)`` or ``None``, ``pn`` the run's constant noise), or ``None``
    when the pass was not all finite (the caller then runs eagerly). The compile time is
    :data:`prognos_torch.filters.sequence.last_compile_seconds`."""
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
    step, record = _step_functions(pf, model, pn, tuple(bs), N, n, u_shape, M, keep_particles)
    if bs:  # the histogram offsets of the batched counts, cached outside the trace
        _arange(R, torch.int64, dev)
    with torch.no_grad():
        # static shapes: each new (T, N, ...) compiles on its own (see _compiled_scan)
        (x, lw), rows = _compiled_scan(
            step, (x0.contiguous(), lw0.contiguous()), ys, packed, record, dynamic=False
        )
    if not (
        all_finite(rows["log_likelihoods"])
        and all_finite(rows["means"])
        and all_finite(rows["covs"])
        and all_finite(x)
    ):
        return None
    flags = torch.zeros((T, *bs), dtype=torch.bool, device=dev)
    rows.update(
        collapsed=flags,
        missing=flags.clone(),
        prior_fallback=torch.zeros((T, *bs), dtype=torch.long, device=dev),
        fading_factors=torch.ones((T, *bs), dtype=dt, device=dev),
    )
    rows.setdefault("particles", None)
    rows.setdefault("log_weights", None)
    return {"rows": rows, "final": (x, lw)}


def _step_functions(pf, model, pn: _PNoise, bs: tuple, N: int, n: int, u_shape, M: int, keep: bool):
    """The scan's step and record for this configuration (kept for reuse)."""
    key = (pf.num_particles, pf.resample_threshold, id(model), id(pn.noise), bs, n, u_shape, keep)
    hit = _STEPS.get(key)
    if hit is not None and hit[0] is model and hit[1] is pn.noise:
        return hit[2], hit[3]
    thr = pf.resample_threshold * N
    log_uniform = -math.log(N)
    P = 0 if u_shape is None else math.prod(u_shape)
    count = math.prod(bs) * N * n

    def resample(x: Tensor, lw: Tensor, W: Tensor, U: Tensor, do: Tensor):
        # STPF step 6: systematic resampling of the runs whose N_eff fell below the threshold
        anc = _systematic_by_counts(_cdf(W), U, traced=True)
        if not bs:  # one run (it resamples: the cond chose this branch)
            return x.index_select(0, anc), torch.full_like(lw, log_uniform)
        anc = torch.where(do[..., None], anc, torch.arange(N, device=anc.device))
        x_r = torch.gather(x, -2, anc.unsqueeze(-1).expand(x.shape))
        lw_r = torch.where(do[..., None], torch.full_like(lw, log_uniform), lw)
        return x_r, lw_r

    def keep_all(x: Tensor, lw: Tensor, W: Tensor, U: Tensor, do: Tensor):
        return x.clone(), lw.clone()

    def step(carry, y: Tensor, packed: Tensor, k):
        x_prev, lw_prev = carry
        u = None if P == 0 else packed[:P].reshape(u_shape)
        u_p = None if u is None else u if u.dim() == 1 else u.unsqueeze(-2)
        eps = box_muller(packed[P : P + M].reshape(-1, 16)).reshape(-1)[:count]
        eps = eps.reshape(x_prev.shape)
        U = packed[P + M :].reshape(*bs, 1)
        _, x = pf._transition_sample(model, x_prev, u_p, k, pn, eps)  # Eq. 15
        x = x.contiguous()  # (the two branches of the cond below must agree in layout)
        lw_un = lw_prev + pf._log_lik(model, x, y, u_p, k, pn)  # Eq. 16
        ll = _log_normaliser(lw_un)
        lw = lw_un - ll.unsqueeze(-1)
        W = lw.exp()
        mean, cov, n_eff = _estimates(W, x)
        do = n_eff < thr
        new = torch.cond(do.any(), resample, keep_all, (x, lw, W, U, do))
        return tuple(new), (mean, cov, n_eff, do, ll, x, lw)

    def record(s, info) -> dict[str, Tensor]:
        mean, cov, n_eff, do, ll, x, lw = info
        row = {"means": mean, "covs": cov, "ess": n_eff, "resampled": do, "log_likelihoods": ll}
        if keep:
            row.update(particles=x, log_weights=lw)
        return row

    if len(_STEPS) > 16:
        _STEPS.clear()
    _STEPS[key] = (model, pn.noise, step, record)
    return step, record
