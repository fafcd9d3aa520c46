"""ROS-ELM as a functional core: one regularised online sequential ELM per measurement channel,
batched over runs (paper 000 Eq. 47-56, Sec. 5 steps 1, 3 and 9).

The ELM modules supply the random hidden layer only (``a``, ``b``, ``g``) and are never modified;
the online state (window, output weights ``beta``, ``K``) lives in an immutable
:class:`ROSELMState` with leading batch dims (Monte Carlo runs, assets). The stateful shell
is :class:`~prognos_torch.prognosis.MeasurementForecaster`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..core.validation import (
    check_finite,
    check_float_tensor,
    check_nonneg,
    check_pos_int,
    has_missing,
)
from ..datasets.windows import shift_append
from .introspect import learner_dtype_device

__all__ = ["ROSELMState", "ros_elm_init", "ros_elm_update", "ros_elm_forecast"]


@dataclass(frozen=True)
class ROSELMState:
    """Online state of one ROS-ELM per measurement channel, batched over runs (paper 000 Eq. 54-56).

    Attributes:
        window: ``(..., C, p)`` the last ``p`` measurements of each channel, oldest first.
        beta: per channel ``(..., L_c)`` output weights (float64); empty for static learners.
        K: per channel ``(..., L_c, L_c)`` ``(H^T H + lambda I)^{-1}`` (float64, Eq. 55).
        n_seen: number of updates that absorbed a (window, target) pair (at least one observed
            entry of ``z``; :func:`ros_elm_init` counts its pairs).
    """

    window: Tensor
    beta: tuple[Tensor, ...]
    K: tuple[Tensor, ...]
    n_seen: int

    @property
    def batch_shape(self) -> torch.Size:
        return self.window.shape[:-2]


def _hidden(elm, x: Tensor) -> Tensor:
    """ELM hidden outputs (paper 000 Eq. 48) in float64, ``(..., p) -> (..., L)``."""
    dt = elm.a.dtype
    return elm.hidden(x.to(dt)).to(torch.float64)


def _pairs(series: Tensor, p: int) -> tuple[Tensor, Tensor]:
    """``series`` ``(..., T)`` -> inputs ``(..., T - p, p)`` and targets ``(..., T - p)``
    (:func:`~prognos_torch.datasets.windows.embed` with batch dims leading)."""
    win = series.unfold(-1, p, 1)  # (..., T - p + 1, p)
    return win[..., :-1, :], series[..., p:]


def ros_elm_init(elms: Sequence[nn.Module], z0: Tensor, p: int, lam: float) -> ROSELMState:
    """ROS-ELM Step I for every channel and run (paper 000 Sec. 5 step 1 and Eq. 54).

    Channel ``c`` of ``z0`` is embedded into ``N0 - p`` pairs ``([z_{t-p+1}, ..., z_t], z_{t+1})``
    and ``K_0 = (H_0^T H_0 + lambda I)^{-1}``, ``beta_0 = K_0 H_0^T T_0`` are solved per run
    (Cholesky, float64). The ELMs supply the random hidden layer only (``a``, ``b``, ``g``); they
    are shared by the runs and not modified.

    Args:
        elms: one :class:`~prognos_torch.learners.ELM` (``n_in = p``, ``n_out = 1``) per channel.
        z0: ``(N0, ..., C)`` initial measurements, time first.
        p: embedding dimension.
        lam: ridge parameter ``lambda >= 0`` (Eq. 52); ``lam == 0`` needs ``N0 - p >= L``
            pairs (paper 000, Step I), else ``ValueError``.
    Returns:
        The :class:`ROSELMState` after ``z0``.
    """
    z0 = check_float_tensor(z0, "z0", "(N0, ..., C)")
    p = check_pos_int(p, "p")
    C = len(elms)
    if C == 0:  # (a state with no channel was returned)
        raise ValueError("elms must hold one ELM per measurement channel (C >= 1), got none")
    if z0.dim() < 2 or z0.shape[-1] != C:
        raise ValueError(
            f"z0 must have shape (N0, ..., C) with C={C} channels, got {tuple(z0.shape)}"
        )
    if z0.shape[0] < p + 1:
        raise ValueError(
            f"z0 must hold N0 >= p + 1 = {p + 1} samples to form a training pair, got N0={z0.shape[0]}"
        )
    check_finite(z0, "z0", "(N0, ..., C)")
    check_nonneg(lam, "lam", numbers_only=True)
    for c, elm in enumerate(elms):
        if not isinstance(getattr(elm, "a", None), Tensor) or not hasattr(elm, "hidden"):
            # (a learner without the random hidden layer raised an AttributeError on 'a')
            raise TypeError(
                f"elms[{c}] must be an ELM (ROS-ELM learns on its random hidden layer a, b, "
                f"Eq. 48), got {type(elm).__name__}"
            )
        if getattr(elm, "n_out", 1) != 1:  # (the ROS-ELM learns one output per channel)
            raise ValueError(
                f"elms[{c}] has n_out={elm.n_out}: each channel's ELM must have n_out=1 "
                "(Eq. 47: one output, the next value of its channel)"
            )
        if getattr(elm, "n_in", p) != p:
            raise ValueError(
                f"elms[{c}] has n_in={elm.n_in}, the embedding dimension p={p}: each ELM takes "
                "the p last values of its channel"
            )
        dev = elm.a.device  # the hidden layer's (Eq. 48), as _hidden uses it
        if dev != z0.device:
            raise ValueError(
                f"elms[{c}] is on {dev}, z0 on {z0.device}: move the ELMs (.to(device)) or "
                f"the measurements to one device"
            )
    z64 = z0.to(torch.float64).movedim(0, -1)  # (..., C, N0)
    betas, Ks = [], []
    for c, elm in enumerate(elms):
        X, T = _pairs(z64[..., c, :], p)  # (..., N', p), (..., N')
        H = _hidden(elm, X)  # (..., N', L)
        L = H.shape[-1]
        if lam == 0 and X.shape[-2] < L:
            # H^T H has rank <= N0 - p < L: its Cholesky factor can still succeed on rounding
            # (K ~ 1e16), so the paper's condition is checked, as ELM.init_online does
            raise ValueError(
                f"channel {c}: z0 gives N0 - p = {X.shape[-2]} training pairs but ROS-ELM "
                f"initialisation without regularisation needs N0 - p >= L = {L} (paper 000, "
                "Step I); pass more samples or lam > 0"
            )
        G = H.mT @ H + lam * torch.eye(L, dtype=H.dtype, device=H.device)
        chol, info = torch.linalg.cholesky_ex(G)
        if bool((info > 0).any()):
            raise ValueError(
                f"channel {c}: H^T H + lam I (Eq. 54) is singular; use lam > 0 or N0 - p >= L"
            )
        eye = torch.eye(L, dtype=H.dtype, device=H.device).expand_as(G)
        K = torch.cholesky_solve(eye, chol)
        K = 0.5 * (K + K.mT)
        beta = torch.cholesky_solve((H.mT @ T.unsqueeze(-1)), chol).squeeze(-1)  # Eq. 54
        betas.append(beta)
        Ks.append(K)
    window = z64[..., -p:]  # (..., C, p)
    return ROSELMState(window, tuple(betas), tuple(Ks), int(z0.shape[0] - p))


def _check_elms_match(elms: Sequence, state: ROSELMState) -> None:
    """The ELMs are those the state was made with: one per channel, with ``beta``'s hidden
    size (an ELM swapped for another raised an IndexError or a matrix-shape error) and the
    window's length ``p`` as input size (else an error on an unnamed ``x``)."""
    if not isinstance(state, ROSELMState):  # (an AttributeError on 'window' or 'beta')
        raise TypeError(
            f"state must be a ROSELMState (from ros_elm_init), got {type(state).__name__}"
        )
    if len(elms) != len(state.beta):
        raise ValueError(
            f"elms has {len(elms)} learners, the state {len(state.beta)} channels: pass the "
            "ELMs the state was made with (one per channel)"
        )
    for c, (elm, beta) in enumerate(zip(elms, state.beta)):
        L = getattr(elm, "n_hidden", None)
        if beta.numel() and L is not None and L != beta.shape[-1]:
            raise ValueError(
                f"elms[{c}] has n_hidden={L}, the state's channel {c} was made with "
                f"{beta.shape[-1]} hidden units: pass the ELMs the state was made with"
            )
        p = state.window.shape[-1]
        n_in = getattr(elm, "n_in", None)
        if n_in is not None and n_in != p:
            raise ValueError(
                f"elms[{c}] has n_in={n_in}, the state's window holds p={p} values per channel: "
                "pass the ELMs the state was made with"
            )


def ros_elm_update(elms: Sequence[nn.Module], state: ROSELMState, z: Tensor) -> ROSELMState:
    """ROS-ELM Step II with the newest measurement ``z`` (paper 000 Eq. 55-56, Sec. 5 step 9).

    Per channel and run, with ``h = g(a P + b)`` of the current window ``P`` and target ``z_c``::

        K_k    = K_{k-1} - K_{k-1} h^T h K_{k-1} / (1 + h K_{k-1} h^T)      (Eq. 55)
        beta_k = beta_{k-1} + K_k h^T (z_c - h beta_{k-1})                   (Eq. 56)

    then the window shifts in ``z`` (Eq. 12-14 on real data).

    A NaN entry of ``z`` marks a missing measurement (inf is refused): that channel of that run
    keeps its ``beta`` and ``K``, and its window shifts in the one-step prediction
    (:func:`ros_elm_forecast`, Eq. 47) in place of the value, so that the window stays on the
    measurements' clock, as a Kalman filter predicts without updating; the other entries update.
    ``n_seen`` counts the updates with at least one observed entry.

    Args:
        z: ``(..., C)`` with the state's batch shape; NaN: missing.
    """
    _check_elms_match(elms, state)
    want = tuple(state.window.shape[:-1])
    z = check_float_tensor(z, "z", f"{want}")
    if tuple(z.shape) != want:
        raise ValueError(f"z must have shape {want} (batch shape + (C,)), got {tuple(z.shape)}")
    if z.device != state.window.device:  # (an error of torch's on mixed devices, or none)
        raise ValueError(
            f"z is on {z.device}, the state on {state.window.device}: pass z on the state's device"
        )
    miss = torch.isnan(z) if has_missing(z, "z", "measurement") else None
    z = z.to(state.window.dtype)
    if miss is not None:  # the prediction stands in for a missing value (Eq. 47)
        z = torch.where(miss, ros_elm_forecast(elms, state, 1)[0], z)
    betas, Ks = [], []
    for c, elm in enumerate(elms):
        beta, K = state.beta[c], state.K[c]
        if beta.numel() == 0:  # static learner: nothing to learn
            betas.append(beta)
            Ks.append(K)
            continue
        h = _hidden(elm, state.window[..., c, :])  # (..., L)
        Kh = (K @ h.unsqueeze(-1)).squeeze(-1)  # (..., L)
        s = 1.0 + (h * Kh).sum(-1, keepdim=True)
        K_new = K - Kh.unsqueeze(-1) * Kh.unsqueeze(-2) / s.unsqueeze(-1)  # Eq. 55
        K_new = 0.5 * (K_new + K_new.mT)
        err = z[..., c] - (h * beta).sum(-1)
        beta_new = beta + (K_new @ h.unsqueeze(-1)).squeeze(-1) * err.unsqueeze(-1)  # Eq. 56
        if miss is not None:  # nothing observed in this channel of a run: no pair to absorb
            m = miss[..., c]
            K_new = torch.where(m[..., None, None], K, K_new)
            beta_new = torch.where(m[..., None], beta, beta_new)
        betas.append(beta_new)
        Ks.append(K_new)
    window = shift_append(state.window, z)
    seen = state.n_seen + (0 if miss is not None and bool(miss.all()) else 1)
    return ROSELMState(window, tuple(betas), tuple(Ks), seen)


def ros_elm_forecast(
    elms: Sequence[nn.Module | Callable[[Tensor], Tensor]], state: ROSELMState, n: int
) -> Tensor:
    """Measurements ``z_{k+1..k+n}`` by successive one-step predictions (paper 000 Sec. 5 step 3).

    ROS-ELM channel ``c``: ``z^_{c,k+j} = h(P) beta_c`` (Eq. 47); a static learner uses its own
    ``forward``. The window of each channel absorbs its forecasts (paper 002 Eq. 12-14).

    Returns:
        ``(n, ..., C)`` float64.
    """
    n = check_pos_int(n, "n")
    _check_elms_match(elms, state)
    w = state.window
    out = []
    for _ in range(n):
        cols = []
        for c, learner in enumerate(elms):
            beta = state.beta[c]
            if beta.numel():
                cols.append((_hidden(learner, w[..., c, :]) * beta).sum(-1))
            else:
                wc = w[..., c, :]
                dt, _dev = learner_dtype_device(learner)
                zc = learner(wc.to(dt))
                # one value per window: (..., 1) (an (..., 2) output lost its second column,
                # a (...,) one gave an error on 'new_value')
                if not isinstance(zc, Tensor) or tuple(zc.shape) != (*wc.shape[:-1], 1):
                    got = tuple(zc.shape) if isinstance(zc, Tensor) else type(zc).__name__
                    raise ValueError(
                        f"elms[{c}] (a static learner) must map the window {tuple(wc.shape)} to "
                        f"{(*wc.shape[:-1], 1)} (one value per window), got {got}"
                    )
                cols.append(zc[..., 0].to(w.dtype))
        zhat = torch.stack(cols, dim=-1)  # (..., C)
        out.append(zhat)
        w = shift_append(w, zhat)
    return torch.stack(out, dim=0)
