"""Batched Monte-Carlo simulation to an event: time-of-event (EOD, EOL) distributions.

A sample of states ``x^i_{k0}`` (drawn from a filter's Gaussian belief, or a particle filter's
weighted particles) is propagated through the model's transition

    x^i_k = f(x^i_{k-1}, u_k, k) [+ w^i_k,  w^i_k ~ N(q_k, Q_k)]

until ``event(x^i_k)`` holds for every sample or the horizon is reached. The event time of
sample ``i`` is ``t0 + dt * j_i`` with ``j_i = min{j >= 1 : event(x^i_{k0+j})}`` (the event is
checked after each step, as progpy's simulator does); samples without an event within the
horizon are censored and kept apart, as in :mod:`prognos_torch.prognosis.rul`.

All samples advance together: ONE batched ``model.transition`` call per step, whatever the
number of samples (progpy's ``MonteCarlo`` runs its simulator once per sample). The event is
evaluated once per chunk of steps on the stacked states of the chunk, so that a step costs the
transition only. Nothing of size ``horizon x samples`` is stored. With ``active_only=True`` the
samples that have met the event are no longer advanced (for row-wise models whose transition is
expensive, e.g. a learner; paths run until every sample has crossed, paper 002).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import check_flag, check_nonneg_int, check_weights, is_int, is_real
from .rul import RULDistribution

__all__ = ["EventPrediction", "sample_belief", "simulate_to_event"]


@dataclass(frozen=True, eq=False)
class EventPrediction:
    """Distribution of the time of an event from Monte-Carlo samples.

    Attributes:
        rul: :class:`~prognos_torch.prognosis.rul.RULDistribution` of the time to the event,
            counted from ``t0`` in steps of ``dt`` (``first_passage`` per sample, weighted pmf,
            ``censored_mass``); its horizon is ``steps_run``.
        t0: time of the initial states.
        final_state: ``(..., N, n)`` state of each sample at its event (for a censored sample:
            at the last step run).
        steps_run: number of steps simulated (the horizon when some sample is censored).
    """

    rul: RULDistribution
    t0: float
    final_state: Tensor
    steps_run: int

    @property
    def time_of_event(self) -> Tensor:
        """``(..., N)`` event time per sample, ``t0 + dt * j_i``; NaN when censored."""
        return self.t0 + self.rul.path_rul

    @property
    def censored_mass(self) -> Tensor:
        """``(...)`` weight of the samples without an event within the horizon."""
        return self.rul.censored_mass

    @property
    def mean(self) -> Tensor:
        """``(...)`` mean event time (NaN where any mass is censored, see ``rul.tol``)."""
        return self.t0 + self.rul.mean

    @property
    def median(self) -> Tensor:
        """``(...)`` median event time (NaN when more than half the mass is censored)."""
        return self.t0 + self.rul.median

    def quantile(self, q) -> Tensor:
        """Event-time quantiles ``t0 + rul.quantile(q)`` (NaN beyond the horizon)."""
        return self.t0 + self.rul.quantile(q)


def sample_belief(belief: GaussianBelief, n: int, generator: torch.Generator) -> Tensor:
    """``n`` draws ``x^i = m + S e^i``, ``e^i ~ N(0, I)``, from a Gaussian belief.

    Args:
        belief: mean ``(..., d)``, square root ``(..., d, d)``.
        n: number of samples ``N >= 1``.
        generator: the source of randomness.
    Returns:
        ``(..., N, d)`` samples.
    """
    if not isinstance(belief, GaussianBelief):
        raise TypeError(f"belief must be a GaussianBelief, got {type(belief)}")
    if not is_int(n) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator)}")
    m, S = belief.mean, belief.chol
    e = torch.randn(
        (*m.shape[:-1], n, m.shape[-1]), generator=generator, dtype=m.dtype, device=m.device
    )
    return m.unsqueeze(-2) + _times(S.unsqueeze(-3), e)


def _times(S: Tensor, e: Tensor) -> Tensor:
    """``S e`` per row of ``e`` written elementwise (independent of how many rows share a call)."""
    return (S * e.unsqueeze(-2)).sum(-1)


def _check_controls(model: StateSpaceModel, controls, x: Tensor) -> Tensor | None:
    p = model.control_dim
    if p == 0:
        if controls is not None:
            raise ValueError("controls were given but the model has control_dim=0")
        return None
    bs = tuple(x.shape[:-2])
    want = f"(H, {p}) or (H, *batch, {p}) with batch = {bs}"
    if not isinstance(controls, Tensor):
        raise ValueError(f"controls are required for this model: a tensor of shape {want}")
    shape = tuple(controls.shape)
    if not (
        controls.dim() >= 2
        and shape[-1] == p
        and (controls.dim() == 2 or shape[1:-1] == bs)
        and shape[0] >= 1
    ):
        raise ValueError(f"controls must have shape {want}, got {shape}")
    if not bool(torch.isfinite(controls).all()):
        raise ValueError(f"controls contain NaN or inf; shape {want}")
    controls = controls.to(dtype=x.dtype, device=x.device)
    return controls if controls.dim() == 2 else controls.unsqueeze(-2)  # broadcast over N


def simulate_to_event(
    model: StateSpaceModel,
    x0: Tensor,
    event: Callable[[Tensor], Tensor],
    *,
    controls: Tensor | None = None,
    max_steps: int | None = None,
    weights: Tensor | None = None,
    t0: float = 0.0,
    dt: float = 1.0,
    k0: int = 0,
    process_noise: bool = False,
    generator: torch.Generator | None = None,
    chunk: int | None = None,
    active_only: bool = False,
) -> EventPrediction:
    """Propagate ``N`` samples together until each meets ``event`` (module docstring).

    Args:
        model: the state-space model; its transition is called once per step on all
            samples ``(..., N, n)``, written into the chunk's state buffer
            (:meth:`~prognos_torch.core.StateSpaceModel.transition_into`: the model's
            ``f_into`` when it has one, else ``transition`` and a copy).
        x0: ``(..., N, n)`` sample states at time ``t0`` (step ``k0``); see :func:`sample_belief`.
        event: ``event(x) -> bool``, ``x`` of any leading shape ``(..., n)``, result ``(...)``:
            the sample has reached the event (e.g. :func:`~prognos_torch.systems.battery.
            battery_eod_event`). It must not depend on the step (it is evaluated on a chunk
            of steps at once).
        controls: ``(H, p)`` (shared) or ``(H, *batch, p)`` controls; row ``j - 1`` is used
            for step ``k0 + j`` (for the battery: :func:`~prognos_torch.systems.battery.
            load_controls` from ``t0``). Required when ``model.control_dim > 0``.
        max_steps: horizon ``H`` in steps; default ``controls.shape[0]`` (required without
            controls).
        weights: ``(..., N)`` normalised sample weights (particles); ``None`` means ``1/N``.
        t0, dt: time of ``x0`` and the step length (only used to report times).
        k0: step index of ``x0`` (the transition of step ``k0 + j`` gets ``k = k0 + j``).
        process_noise: add ``w_k ~ N(q_k, Q_k)`` of the model each step (``generator``
            required); ``False`` propagates the samples noise-free, so all the spread comes from
            ``x0``.
        generator: source of the process noise.
        chunk: steps between event checks; does not change the result (the noise is drawn
            step by step, in the same order whatever the chunk). Default: 32 steps, fewer for
            large sample sets (the chunk's states stay within about 2 MB).
        active_only: after each chunk, advance only the samples without an event (their rows
            of the flattened ``(..., N)`` leading dims). The noise is still drawn for every
            sample, so the random stream and, up to the round-off of a transition evaluated on
            fewer rows, the result equal those of ``active_only=False``. Needs a row-wise
            transition, no controls or shared ``(H, p)`` controls, and constant noise with an
            ``(n, n)`` square root.
    Returns:
        :class:`EventPrediction`. The loop runs under ``torch.inference_mode`` (event times are
        step counts; nothing in the result carries a gradient).

    Raises:
        TypeError: an argument of the wrong type, named.
        ValueError: an argument of the wrong shape or value, named with the expected shape.
    """
    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"model must be a StateSpaceModel, got {type(model)}")
    if not callable(event):
        raise TypeError("event must be a callable event(x (..., n)) -> bool (...)")
    n = model.state_dim
    if not isinstance(x0, Tensor) or x0.dim() < 2 or x0.shape[-1] != n:
        got = tuple(x0.shape) if isinstance(x0, Tensor) else type(x0)
        raise ValueError(f"x0 must be a tensor of shape (..., N, {n}) (N samples), got {got}")
    if not x0.is_floating_point() or not bool(torch.isfinite(x0).all()):
        raise ValueError(f"x0 must be finite floating point, shape (..., N, {n})")
    if x0.dtype in (torch.float16, torch.bfloat16):  # (the state drifted: no event, no error)
        raise TypeError(f"x0 has dtype {x0.dtype}: simulate in float32 or float64")
    us = _check_controls(model, controls, x0)
    if max_steps is None:
        if us is None:
            raise ValueError("max_steps is required when no controls are given")
        max_steps = us.shape[0]
    if not is_int(max_steps) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    max_steps = int(max_steps)  # (a NumPy count came back as steps_run)
    k0 = check_nonneg_int(k0, "k0")  # (a float k0 reached the transition as k)
    if us is not None and us.shape[0] < max_steps:
        raise ValueError(
            f"controls cover {us.shape[0]} steps, fewer than max_steps = {max_steps}; "
            "shape (H, ..., p) with H >= max_steps"
        )
    for name, v in (("t0", t0), ("dt", dt)):
        if not is_real(v) or not math.isfinite(v):
            raise ValueError(f"{name} must be a finite number, got {v!r}")
    if dt <= 0:
        raise ValueError(f"dt must be positive, got {dt!r}")
    if chunk is None:
        chunk = max(2, min(32, 2**18 // max(1, x0.numel())))
    if not is_int(chunk) or chunk < 1:
        raise ValueError(f"chunk must be a positive int, got {chunk!r}")
    chunk = int(chunk)
    process_noise = check_flag(process_noise, "process_noise")  # ("no" was read as True)
    if process_noise and not isinstance(generator, torch.Generator):
        raise TypeError("process_noise=True needs a torch.Generator (generator=...)")
    w = check_weights(weights, x0.shape[:-1][:-1], x0.shape[-2], x0.device)
    if not isinstance(active_only, bool):
        raise TypeError(f"active_only must be a bool, got {active_only!r}")
    if active_only:
        if us is not None and us.dim() != 2:
            raise ValueError("active_only=True needs shared controls of shape (H, p)")
        if callable(model.chol_Q) or callable(model.q):
            raise ValueError("active_only=True needs constant process noise (chol_Q, q)")
        nz = model.checked_noise(k0 + 1, x0.shape[:-1], x0)
        if nz.chol_Q.dim() != 2 or (nz.q is not None and nz.q.dim() != 1):
            raise ValueError("active_only=True needs a shared (n, n) chol_Q and an (n,) q")

    # event times are step counts, not differentiable: skip autograd bookkeeping in the loop
    with torch.inference_mode():
        first, final, step = _loop(
            model, x0, event, us, max_steps, k0, process_noise, generator, chunk, active_only
        )
    rul = _distribution(first.clone(), w, step, float(dt))
    return EventPrediction(rul=rul, t0=float(t0), final_state=final.clone(), steps_run=step)


def _loop(model, x0, event, us, max_steps, k0, process_noise, generator, chunk, active_only):
    x = x0
    lead = x.shape[:-1]  # (..., N)
    rows = None  # active_only: flat indices of the samples still without an event
    first = torch.full(lead, -1, dtype=torch.int64, device=x.device)
    final = x0.clone()
    done = torch.zeros(lead, dtype=torch.bool, device=x.device)
    const_noise = not (callable(model.chol_Q) or callable(model.q))
    noise = model.checked_noise(k0 + 1, lead, x) if process_noise and const_noise else None
    into = model.f_into or model.transition_into  # (x, u, k, out) -> out
    step = 0
    while step < max_steps:
        C = min(chunk, max_steps - step)
        # the chunk's states, component-major: (C, n, ..., N), shown to the event as
        # (C, ..., N, n); component-major rows are contiguous for models that keep their
        # state that way (the battery's step does)
        buf = torch.empty((C, x.shape[-1], *lead), dtype=x.dtype, device=x.device)
        states = buf.movedim(1, -1)
        # each step is written into its row of the chunk's buffer (model.transition_into: no
        # copy for models with f_into); the chunk's controls are split once
        outs = states.unbind(0)
        uc = (None,) * C if us is None else us[step : step + C].unbind(0)
        for c in range(C):
            k = k0 + step + c + 1
            if rows is not None:
                x = _advance_rows(model, x, rows, uc[c], k, noise, process_noise, generator)
                outs[c].copy_(x)
                continue
            x = into(x, uc[c], k, outs[c])
            if process_noise:
                nz = noise if noise is not None else model.checked_noise(k, lead, x)
                e = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
                x.add_(_times(nz.chol_Q, e))
                if nz.q is not None:
                    x.add_(nz.q)
        hit = torch.as_tensor(event(states), device=x.device)
        if hit.dtype != torch.bool or tuple(hit.shape) != (C, *lead):
            raise ValueError(
                f"event must return a bool tensor of the states' leading shape {(C, *lead)}, "
                f"got {hit.dtype} {tuple(hit.shape)}"
            )
        new = hit.any(0) & ~done
        if bool(new.any()):
            j = torch.argmax(hit.to(torch.uint8), dim=0)  # first step of the chunk with the event
            first = torch.where(new, step + j + 1, first)
            at = states.gather(0, j[None, ..., None].expand(1, *x.shape))[0]
            final = torch.where(new[..., None], at, final)
            done = done | new
        step += C
        if bool(done.all()):
            break
        if active_only:
            rows = torch.nonzero(~done.reshape(-1)).flatten()
    return first, torch.where(done[..., None], final, x), step


def _advance_rows(model, x, rows, u, k, noise, process_noise, generator):
    """One step of the samples ``rows`` of the flattened leading dims (the others stay); the
    noise is drawn for all samples, as in the full step."""
    n = x.shape[-1]
    flat = x.reshape(-1, n)
    xa = model.transition(flat[rows], u, k)
    if process_noise:
        e = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        xa = xa + _times(noise.chol_Q, e.reshape(-1, n)[rows])
        if noise.q is not None:
            xa = xa + noise.q
    out = flat.clone()
    out[rows] = xa
    return out.reshape(x.shape)


def _distribution(first: Tensor, w: Tensor, horizon: int, dt: float) -> RULDistribution:
    """The :class:`RULDistribution` of first-passage steps (``-1``: censored) and weights."""
    idx = torch.where(first > 0, first - 1, torch.full_like(first, horizon))
    mass = torch.zeros((*w.shape[:-1], horizon + 1), dtype=torch.float64, device=w.device)
    mass.scatter_add_(-1, idx, w)
    pmf, censored = mass[..., :horizon], mass[..., horizon]
    support = torch.arange(1, horizon + 1, dtype=torch.float64, device=w.device) * dt
    crossing = pmf.sum(-1)
    expectation = (pmf * support).sum(-1) / crossing
    withheld = (censored > 0) | (crossing <= 0)
    expectation = torch.where(withheld, torch.full_like(expectation, math.nan), expectation)
    return RULDistribution(
        first_passage=first,
        weights=w,
        pmf=pmf,
        censored_mass=censored,
        expectation=expectation,
        dt=dt,
        tol=0.0,
    )
