"""Kalman-filter optimisers with a ``torch.optim`` interface (paper 003 Sec. IV, Eq. 44-46).

Training is state estimation. The state is the parameter vector ``theta`` (Eq. 44, see
:class:`~prognos_torch.optim.params.ParameterBridge`), which follows a random walk and is
measured through the model::

    theta_k = theta_{k-1} + w_k,        w_k ~ N(0, Q)          (Eq. 45)
    t_k     = g(theta_k, u_k) + v_k,    v_k ~ N(0, R)          (Eq. 46)

where ``u_k`` is a sample (or a mini-batch) of inputs and ``t_k`` its targets (for a mini-batch,
the outputs flattened sample after sample, with ``R`` repeated block-diagonally). The optimiser
builds this :class:`~prognos_torch.core.model.StateSpaceModel` at every step (``f=None``, the
random walk the engine propagates exactly; ``h`` closing over the mini-batch inputs) and calls
the library's one filter engine, :meth:`GaussianFilter.step`; it has no filter arithmetic of its
own. Any engine configuration can be used: EKF (``h`` linearised by ``torch.func`` Jacobians),
SRUKF (paper 003 Eq. 10-30), ImSRUKF (SRUKF + the Sage-Husa estimator of Eq. 40-43), SCKF, the
strong-tracking variants, ...

The belief ``N(theta, P)`` is kept in float64 in ``optimizer.state`` whatever the module dtype,
and survives ``state_dict()``/``load_state_dict()`` unchanged (``torch.optim`` would cast state
tensors to the parameter dtype; the belief is stored under a key that is not a parameter and is
checked on load), so that a resumed run is bit-identical to an uninterrupted one.

Batched Monte Carlo: ``runs=R`` with ``theta0`` ``(R, n)`` trains ``R`` independent parameter
vectors (e.g. ``R`` initialisations of an ANFIS) on the same data in one vectorised filter call
per step; with ``per_run_data=True`` each run has its own data (inputs ``(R, *x)``, targets
``(R, *out)``, e.g. ``R`` noise realisations; the model is evaluated with ``torch.func.vmap``
over the runs). The module's parameters are then left untouched; use
:meth:`KalmanOptimizer.predict` or :attr:`KalmanOptimizer.theta`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields, replace
from itertools import chain

import torch
from torch import Tensor, nn
from torch.func import vmap
from torch.optim.optimizer import _global_optimizer_post_hooks, _global_optimizer_pre_hooks

from ..adapt.noise import MovingWindow, NoiseEstimatorState, SageHusa
from ..adapt.strong_tracking import StrongTracking, StrongTrackingState
from ..core.belief import GaussianBelief
from ..core.linalg import tria
from ..core.model import StateSpaceModel
from ..core.validation import check_matches
from ..filters.gaussian import FilterState, GaussianFilter, StepInfo, Taylor
from ..filters.variants import make_filter
from .params import ParameterBridge

__all__ = [
    "KalmanOptimizer",
    "KalmanStep",
    "EKF",
    "SRUKF",
    "ImSRUKF",
    "noise_factor",
    "OPTIMIZER_NOISE",
]

_STATE_KEY = "kalman"


@dataclass(frozen=True)
class KalmanStep:
    """What :meth:`KalmanOptimizer.step` returns (batch dims ``(R,)`` with ``runs=R``, else ``()``).

    Attributes:
        loss: mean squared innovation ``mean_j (t_j - z_j)^2`` over the measurement vector, under
            the prior (before the update). For the EKF ``z = g(theta_{k-1}, u_k)``, so this is the
            pre-update mean squared error; sigma-point filters use their predicted measurement.
        info: the engine's full :class:`~prognos_torch.filters.gaussian.StepInfo`.

    ``nis`` (normalised innovation squared), ``fading_factor`` (``lambda_k``, 1 without strong
    tracking) and ``log_likelihood`` are read from ``info`` (computed on first access).
    """

    loss: Tensor
    info: StepInfo

    @property
    def nis(self) -> Tensor:
        return self.info.nis

    @property
    def fading_factor(self) -> Tensor:
        return self.info.fading_factor

    @property
    def log_likelihood(self) -> Tensor:
        return self.info.log_likelihood

    def item(self) -> float:
        """The loss as a Python float (mean over runs)."""
        return float(self.loss.mean())


# ---------------------------------------------------------------------- option parsing
def noise_factor(value, dim: int, name: str, *, allow_singular: bool, device=None) -> Tensor:
    """A lower square-root factor ``(dim, dim)`` float64 of a covariance given as a scalar
    variance (``v I``), a vector of variances ``(dim,)`` (``diag(v)``) or a matrix ``(dim, dim)``.

    With ``allow_singular`` a positive semi-definite matrix (e.g. ``Q = 0``) is accepted and
    factorised through its eigen-decomposition; otherwise it must be positive definite.
    """
    if isinstance(value, bool):
        raise TypeError(f"{name} must be a number or a tensor, got {value!r}")
    try:
        v = torch.as_tensor(value, dtype=torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(
            f"{name} must be a number, a vector or a matrix, got {type(value)}"
        ) from exc
    if device is not None:
        v = v.to(device)
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{name} contains non-finite values")
    strict = "> 0" if not allow_singular else ">= 0"
    if v.dim() == 0 or v.dim() == 1:
        if v.dim() == 1 and v.shape[0] != dim:
            raise ValueError(
                f"{name} as a vector of variances must have shape ({dim},), got {tuple(v.shape)}"
            )
        ok = (v >= 0) if allow_singular else (v > 0)
        if not bool(ok.all()):
            raise ValueError(f"{name} variances must be {strict}, got {value}")
        d = v.sqrt().expand(dim) if v.dim() == 0 else v.sqrt()
        return torch.diag_embed(d)
    if v.dim() != 2 or tuple(v.shape) != (dim, dim):
        raise ValueError(
            f"{name} must be a scalar, a vector ({dim},) or a matrix ({dim}, {dim}), got shape "
            f"{tuple(v.shape)}"
        )
    scale = float(v.abs().max()) if v.numel() else 0.0
    if not bool(torch.allclose(v, v.mT, rtol=1e-10, atol=1e-12 * scale + 1e-300)):
        raise ValueError(f"{name} must be a symmetric matrix ({dim}, {dim})")
    L, info = torch.linalg.cholesky_ex(v)
    if int(info) == 0:
        return L
    w, V = torch.linalg.eigh(0.5 * (v + v.mT))
    if not allow_singular or bool((w < -1e-12 * max(scale, 1e-300)).any()):
        raise ValueError(f"{name} must be positive {'semi-' if allow_singular else ''}definite")
    return tria(V * w.clamp_min(0.0).sqrt().unsqueeze(-2))


#: The noise estimator of the ``"imsrukf"`` optimiser (paper 003 Eq. 41 and 43, see
#: :class:`KalmanOptimizer`): ``Q`` and ``R`` only, ``Q`` diagonal.
OPTIMIZER_NOISE = SageHusa(estimate=("Q", "R"), diagonal=True)


def _resolve_filter(filt, fading, noise) -> GaussianFilter:
    if isinstance(filt, str):
        # the optimiser face's fast path: random walk, prior factor by a Cholesky of S S^T + Q
        base = replace(make_filter(filt), prior="cholesky")
        if filt.lower() == "imsrukf":
            base = replace(base, noise=OPTIMIZER_NOISE)
    elif isinstance(filt, GaussianFilter):
        base = filt
    else:
        raise TypeError(f"filter must be a filter name or a GaussianFilter, got {type(filt)}")
    changes = {}
    if fading is not None:
        if fading is False:
            changes["fading"] = None
        elif fading is True:
            changes["fading"] = StrongTracking()
        elif isinstance(fading, (StrongTracking, int, float)):
            changes["fading"] = fading
        else:
            raise TypeError("fading must be None, True/False, a float >= 1 or StrongTracking")
    if noise is not None:
        if noise is False:
            changes["noise"] = None
        elif noise is True:
            changes["noise"] = SageHusa()
        elif isinstance(noise, (SageHusa, MovingWindow)):
            changes["noise"] = noise
        else:
            raise TypeError("noise must be None, True/False, SageHusa or MovingWindow")
    return replace(base, **changes) if changes else base


def _resolve_module(params, module) -> tuple[nn.Module, list[str] | None]:
    """``(module, names)`` from the ``params``/``module`` arguments (names None: default)."""
    if isinstance(params, nn.Module):
        if module is not None and module is not params:
            raise ValueError("module must be omitted or be the module passed as params")
        return params, None
    if module is None:
        raise ValueError(
            "module is required when params is an iterable of parameters "
            "(KalmanOptimizer(module.parameters(), module=module))"
        )
    if not isinstance(module, nn.Module):
        raise TypeError(f"module must be a torch.nn.Module, got {type(module)}")
    if isinstance(params, Tensor) or not isinstance(params, Iterable):
        raise TypeError("params must be a module or an iterable of its parameters")
    by_id = {id(p): n for n, p in module.named_parameters()}
    names = []
    for p in params:
        if isinstance(p, tuple) and len(p) == 2:  # named_parameters()
            p = p[1]
        if isinstance(p, dict):
            raise ValueError("KalmanOptimizer supports a single parameter group (like LBFGS)")
        if not isinstance(p, Tensor) or id(p) not in by_id:
            raise ValueError("params must contain parameters of module only")
        names.append(by_id[id(p)])
    if not names:
        raise ValueError("params is empty: no parameters to train")
    return module, names


def _clone_state(obj):
    """A copy of a frozen dataclass of tensors (``None`` stays ``None``)."""
    if obj is None:
        return None
    return replace(
        obj,
        **{k: (v.clone() if isinstance(v, Tensor) else v) for k, v in _dataclass_dict(obj).items()},
    )


def _dataclass_dict(obj) -> dict | None:
    if obj is None:
        return None
    return {f.name: getattr(obj, f.name) for f in fields(obj)}


# ---------------------------------------------------------------------- the optimiser
class KalmanOptimizer(torch.optim.Optimizer):
    """Train a module by Gaussian filtering of its parameters (paper 003 Eq. 44-46).

    One parameter group (like ``LBFGS``); its options are ``param_groups[0]``. Usage::

        opt = KalmanOptimizer(model, filter="imsrukf", P0=1.0, Q=1e-6, R=1e-3)
        for x, t in loader:
            opt.step(x, t)          # or opt.step(lambda: (x, t))

    Args:
        params: the module to train (its parameters with ``requires_grad=True`` form ``theta``),
            or an iterable of some of its parameters (then ``module`` is required).
        module: the module, when ``params`` is an iterable of parameters.
        filter: a filter name of :func:`~prognos_torch.filters.variants.make_filter` (``"ekf"``,
            ``"srukf"``, ``"imsrukf"``, ``"ukf"``, ``"ckf"``, ``"sckf"``, ``"stekf"``, ``"stukf"``,
            ``"stsckf"``) or a configured :class:`GaussianFilter`.
        P0: prior covariance of ``theta_0``: scalar variance, ``(n,)`` variances, ``(n, n)``, or
            a dict ``{parameter name: variance}`` (:meth:`ParameterBridge.expand`).
        Q: random-walk covariance of Eq. 45 (as ``P0``; ``0`` allowed).
        R: measurement-noise covariance of ONE output vector (scalar, ``(n_out,)`` or
            ``(n_out, n_out)`` with ``n_out`` the last dimension of the model output); a mini-batch
            uses it block-diagonally.
        fading: ``None`` (the filter's own setting), ``False`` (off), ``True``
            (``StrongTracking()``), a constant factor ``>= 1`` or a ``StrongTracking``.
        noise: ``None`` (the filter's own; for ``filter="imsrukf"`` :data:`OPTIMIZER_NOISE`),
            ``False`` (off), ``True`` (``SageHusa()``, all of paper 003 Eq. 40-43) or a
            ``SageHusa``/``MovingWindow``. A noise estimator or strong tracking needs a constant
            measurement size (same mini-batch size at every step).
        runs: ``None`` for one run, or ``R`` for ``R`` independent runs in one batch.
        per_run_data: with ``runs=R``, every run gets its own data: ``step`` and ``predict``
            take inputs ``(R, *x)`` and targets ``(R, *out)`` (e.g. ``R`` noise realisations);
            default ``False``: all runs see the same inputs and targets.
        theta0: initial mean ``(n,)`` (or ``(R, n)`` with ``runs``); default: the module's
            current parameters (repeated over runs).
        jacobian: ``"auto"``, ``"rev"``, ``"fwd"`` or ``"autograd"``: how the EKF differentiates
            ``g`` (see :meth:`ParameterBridge.jacobian`; ``"auto"`` uses the learner's closed-form
            derivatives when it has them, as ELM and ANFIS do).
        chunk_size: vectorise at most this many parameter vectors / Jacobian products at once.

    ImSRUKF in the optimiser face. Paper 003 estimates all four noise statistics (Eq. 40-43).
    With the random walk of Eq. 45, Eq. 40 makes ``q`` the running mean of the parameter
    updates, which the next prediction adds again: a persistent drift; and Eq. 42's ``r`` is a
    bias of the filter's measurement prediction that the trained module does not carry. On the
    Lorenz set-up of paper 003 (``tests/test_optim.py``, 10 ANFIS initialisations, one pass)
    both ruin the training: mean test MAE 0.21 when ``q`` is estimated too, 0.23 with ``r``,
    0.59 with both, against 0.0034 with ``Q`` and ``R`` only. So ``filter="imsrukf"``
    estimates ``Q`` and ``R`` only (Eq. 41, 43), ``Q`` as a diagonal (:data:`OPTIMIZER_NOISE`;
    the rank-one terms of Eq. 41 leave a full 44 x 44 estimate indefinite at almost every step,
    so it is projected every step; the full form gave MAE 0.0072 and costs an eigendecomposition
    per step). Pass ``noise=SageHusa()`` for the paper's full estimator. Note that while ``P``
    is being learned, ``e e^T`` is mostly smaller than ``H P H^T``, so the ``R`` of Eq. 43 is
    mostly negative and held at the estimator's positive floor (the filter then trusts the
    targets and the spread of ``P``); on Lorenz this was more accurate than SRUKF with fixed
    ``R`` after 5 passes (mean test MAE 0.0017 vs 0.0050), less accurate after one (0.0034 vs
    0.0012).
    """

    def __init__(
        self,
        params: nn.Module | Iterable,
        module: nn.Module | None = None,
        *,
        filter: str | GaussianFilter = "ekf",
        P0=1.0,
        Q=0.0,
        R=1.0,
        fading=None,
        noise=None,
        runs: int | None = None,
        per_run_data: bool = False,
        theta0: Tensor | None = None,
        jacobian: str = "auto",
        chunk_size: int | None = None,
    ) -> None:
        module, names = _resolve_module(params, module)
        bridge = ParameterBridge(module, names)
        if runs is not None and (isinstance(runs, bool) or not isinstance(runs, int) or runs < 1):
            raise ValueError(f"runs must be None or a positive int, got {runs!r}")
        if jacobian not in ("auto", "rev", "fwd", "autograd"):
            raise ValueError(
                f"jacobian must be 'auto', 'rev', 'fwd' or 'autograd', got {jacobian!r}"
            )
        if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
            raise ValueError(f"chunk_size must be None or a positive int, got {chunk_size!r}")
        if not isinstance(per_run_data, bool):
            raise TypeError(f"per_run_data must be a bool, got {type(per_run_data)}")
        if per_run_data and runs is None:
            raise ValueError("per_run_data=True needs runs=R (the number of runs)")
        defaults = dict(
            filter=filter,
            P0=P0,
            Q=Q,
            R=R,
            fading=fading,
            noise=noise,
            runs=runs,
            per_run_data=per_run_data,
            jacobian=jacobian,
            chunk_size=chunk_size,
        )
        self.bridge = bridge
        self.module = module
        super().__init__(bridge.parameters(), defaults)
        self._setup()
        self.state[_STATE_KEY] = self._initial_state(theta0)

    def __getstate__(self) -> dict:
        # torch.optim keeps only defaults, state and param_groups; copy.deepcopy and pickle of
        # a Kalman optimiser also need its bridge, module and configured filter. The per-shape
        # step models close over this optimiser's bridge: rebuilt by the copy.
        state = self.__dict__.copy()
        state["_models"], state["_inputs"] = {}, [None]
        return state

    def add_param_group(self, param_group: dict) -> None:
        if getattr(self, "param_groups", None):
            raise ValueError("KalmanOptimizer supports a single parameter group (like LBFGS)")
        super().add_param_group(param_group)

    # ------------------------------------------------------------------ configuration
    def _setup(self) -> None:
        """Derive the filter and noise factors from ``param_groups[0]`` (also after a load)."""
        g = self.param_groups[0]
        n, dev = self.bridge.numel, self.bridge.device
        self._filter = _resolve_filter(g["filter"], g["fading"], g["noise"])
        P0, Q = g["P0"], g["Q"]
        P0 = self.bridge.expand(P0, "P0") if isinstance(P0, dict) else P0
        Q = self.bridge.expand(Q, "Q") if isinstance(Q, dict) else Q
        self._chol_P0 = noise_factor(P0, n, "P0", allow_singular=False, device=dev)
        self._chol_Q = noise_factor(Q, n, "Q", allow_singular=True, device=dev)
        R = torch.as_tensor(g["R"], dtype=torch.float64, device=dev)
        n_out = 1 if R.dim() == 0 else R.shape[0]
        self._chol_R1 = noise_factor(R, n_out, "R", allow_singular=False, device=dev)
        self._R_scalar = R.dim() == 0
        self._chol_R_cache: dict[int, Tensor] = {}
        self._out_shapes: dict[tuple, torch.Size] = {}
        self._models: dict[tuple, StateSpaceModel] = {}
        self._inputs: list = [None]

    def _initial_state(self, theta0) -> dict:
        runs, n = self.runs, self.bridge.numel
        if theta0 is None:
            mean = self.bridge.flatten()
            if runs is not None:
                mean = mean.expand(runs, n).clone()
        else:
            if not isinstance(theta0, Tensor):
                raise TypeError("theta0 must be a torch.Tensor")
            want = (n,) if runs is None else (runs, n)
            if tuple(theta0.shape) != want:
                raise ValueError(f"theta0 must have shape {want}, got {tuple(theta0.shape)}")
            if theta0.device != self.bridge.device:
                raise ValueError(
                    f"theta0 is on {theta0.device}, the module on {self.bridge.device}"
                )
            if not bool(torch.isfinite(theta0).all()):
                raise ValueError("theta0 contains non-finite values")
            mean = theta0.detach().to(torch.float64).clone()
        chol = self._chol_P0.expand(*mean.shape[:-1], n, n).clone()
        if runs is None:
            self.bridge.assign(mean)
        return {"mean": mean, "chol": chol, "fading": None, "noise": None, "step": 0}

    @property
    def runs(self) -> int | None:
        return self.param_groups[0]["runs"]

    @property
    def filter(self) -> GaussianFilter:
        """The configured engine filter."""
        return self._filter

    # ------------------------------------------------------------------ belief access
    @property
    def theta(self) -> Tensor:
        """Posterior mean of ``theta``: ``(n,)`` or ``(R, n)``, float64 (a copy)."""
        return self.state[_STATE_KEY]["mean"].clone()

    @property
    def belief(self) -> GaussianBelief:
        """The current float64 belief ``N(theta, P)`` over the parameters (a copy)."""
        s = self.state[_STATE_KEY]
        return GaussianBelief(s["mean"].clone(), s["chol"].clone())

    @property
    def filter_state(self) -> FilterState:
        """The engine's :class:`FilterState` (belief, fading and noise-estimator states; a copy)."""
        fs = self._filter_state()
        return FilterState(
            GaussianBelief(fs.belief.mean.clone(), fs.belief.chol.clone()),
            _clone_state(fs.fading),
            _clone_state(fs.noise),
        )

    def _filter_state(self) -> FilterState:
        s = self.state[_STATE_KEY]
        fst = None if s["fading"] is None else StrongTrackingState(**s["fading"])
        nst = None if s["noise"] is None else NoiseEstimatorState(**s["noise"])
        return FilterState(GaussianBelief(s["mean"], s["chol"]), fst, nst)

    def parameter_covariance(self) -> Tensor:
        """Posterior covariance of ``theta``: ``(n, n)`` or ``(R, n, n)`` float64."""
        S = self.state[_STATE_KEY]["chol"]
        return S @ S.mT

    def parameter_std(self) -> Tensor:
        """Posterior standard deviations of ``theta``: ``(n,)`` or ``(R, n)`` float64."""
        S = self.state[_STATE_KEY]["chol"]
        return S.square().sum(-1).sqrt()

    @torch.no_grad()
    def predict(self, inputs: Tensor) -> Tensor:
        """Model outputs at the posterior mean: ``module(inputs)`` for one run, ``(R, *out)``
        with ``runs=R`` (module dtype). With ``per_run_data``, ``inputs`` is ``(R, *x)``."""
        x = self._check_inputs(inputs)
        mean, b, chunk = self.state[_STATE_KEY]["mean"], self.bridge, self._chunk
        if self.per_run_data:
            return vmap(lambda th, xr: b.batched(th, xr, chunk_size=chunk))(mean, x)
        return b.batched(mean, x, chunk_size=chunk)

    @property
    def per_run_data(self) -> bool:
        """Whether every run has its own inputs and targets (``(R, ...)``)."""
        return bool(self.param_groups[0].get("per_run_data", False))

    # ------------------------------------------------------------------ the step
    @property
    def _chunk(self) -> int | None:
        return self.param_groups[0]["chunk_size"]

    def _check_inputs(self, inputs) -> Tensor:
        b = self.bridge
        if not isinstance(inputs, Tensor):
            raise TypeError(f"inputs must be a torch.Tensor, got {type(inputs)}")
        check_matches(inputs, "inputs", b.dtype, b.device)
        if self.per_run_data and (inputs.dim() < 1 or inputs.shape[0] != self.runs):
            raise ValueError(
                f"inputs must have shape (runs={self.runs}, ...) with per_run_data=True, got "
                f"{tuple(inputs.shape)}"
            )
        return inputs

    def _check_batch(self, inputs, targets) -> tuple[Tensor, Tensor, torch.Size]:
        b = self.bridge
        x = self._check_inputs(inputs)
        per_run = self.per_run_data
        key = tuple(x.shape)
        out_shape = self._out_shapes.get(key)
        if out_shape is None:  # the output of one run (per-run data: for its own inputs)
            theta = self.state[_STATE_KEY]["mean"].reshape(-1, b.numel)[0]
            out_shape = b.functional(theta, x[0] if per_run else x).shape
            self._out_shapes[key] = out_shape
        want = ((self.runs,) if per_run else ()) + tuple(out_shape)
        if not isinstance(targets, Tensor):
            raise TypeError(f"targets must be a torch.Tensor of shape {want}")
        if tuple(targets.shape) != want:
            raise ValueError(
                f"targets must have shape {want} (the model output for inputs of "
                f"shape {tuple(x.shape)}), got {tuple(targets.shape)}"
            )
        check_matches(targets, "targets", b.dtype, b.device)
        return x, targets, out_shape

    def _chol_R(self, out_shape: torch.Size) -> Tensor:
        M = math.prod(out_shape)
        S = self._chol_R_cache.get(M)
        if S is not None:
            return S
        if self._R_scalar:
            S = self._chol_R1[0, 0] * torch.eye(M, dtype=torch.float64, device=self.bridge.device)
        else:
            n_out = self._chol_R1.shape[0]
            if len(out_shape) == 0 or out_shape[-1] != n_out:
                raise ValueError(
                    f"R is ({n_out}, {n_out}) per output vector, but the model output has shape "
                    f"{tuple(out_shape)} (its last dimension must be {n_out})"
                )
            eye = torch.eye(M // n_out, dtype=torch.float64, device=self.bridge.device)
            S = torch.kron(eye, self._chol_R1.contiguous())  # block diagonal: one R per sample
        self._chol_R_cache[M] = S
        return S

    def _model(self, x: Tensor, out_shape: torch.Size) -> StateSpaceModel:
        """Paper 003 Eq. 45-46 for this mini-batch: random walk, ``h(theta) = g(theta, x)``.

        The model is built once per mini-batch shape; its ``h`` reads the current inputs from
        ``self._inputs``, set here at every step.
        """
        b, chunk = self.bridge, self._chunk
        key = (tuple(x.shape), tuple(out_shape))
        self._inputs[0] = x
        model = self._models.get(key)
        if model is not None:
            return model
        M = math.prod(out_shape)
        mode = self.param_groups[0]["jacobian"]
        if mode == "auto" and not self._closed_form_applies(x):
            mode = "fwd" if b.numel <= M else "autograd"
        inputs = self._inputs
        if self.per_run_data:  # run r evaluates g(theta_r, x_r): vmap over the runs
            if mode == "autograd":  # reverse mode through autograd does not vmap
                mode = "rev"
            return self._store_model(key, self._per_run_model(b, M, out_shape, mode, chunk))
        if isinstance(self._filter.rule, Taylor) and mode in ("auto", "autograd"):
            # the EKF asks for h and then for its Jacobian at the same point: one pass (the
            # learner's closed form, or forward + reverse) gives both, the Jacobian is handed
            # over by identity of the evaluation point
            last: list = [None, None]

            def h(th, u, k):
                out, J = b.measurement_and_jacobian(th, inputs[0], chunk_size=chunk, mode=mode)
                last[0], last[1] = th, J
                return out

            def jac_h(th, u, k):
                if last[0] is th:
                    J, last[0], last[1] = last[1], None, None
                    return J
                return b.jacobian(th, inputs[0], mode=mode, chunk_size=chunk)

        else:

            def h(th, u, k):
                return b.measurement(th, inputs[0], chunk_size=chunk)

            def jac_h(th, u, k):
                return b.jacobian(th, inputs[0], mode=mode, chunk_size=chunk)

        return self._store_model(key, self._random_walk_model(h, jac_h, M, out_shape))

    def _random_walk_model(self, h, jac_h, M: int, out_shape) -> StateSpaceModel:
        return StateSpaceModel(
            f=None,  # Eq. 45: theta_k = theta_{k-1} + w_k (exact in the engine)
            h=h,  # Eq. 46: t_k = g(theta_k, u_k) + v_k
            state_dim=self.bridge.numel,
            obs_dim=M,
            chol_Q=self._chol_Q,
            chol_R=self._chol_R(out_shape),
            batched=True,
            jac_h=jac_h,
        )

    def _store_model(self, key, model: StateSpaceModel) -> StateSpaceModel:
        self._models[key] = model
        return model

    def _per_run_model(self, b, M: int, out_shape, mode: str, chunk) -> StateSpaceModel:
        """Eq. 45-46 with per-run data: ``theta`` ``(R, ..., n)``, inputs ``(R, *x)``."""
        inputs = self._inputs

        def h(th, u, k):
            return vmap(lambda t, xr: b.measurement(t, xr, chunk_size=chunk))(th, inputs[0])

        def jac_h(th, u, k):
            return vmap(lambda t, xr: b.jacobian(t, xr, mode=mode, chunk_size=chunk))(th, inputs[0])

        return self._random_walk_model(h, jac_h, M, out_shape)

    def _engine_state(self, model: StateSpaceModel) -> FilterState:
        s = self.state[_STATE_KEY]
        filt = self._filter
        if (filt.noise is not None and s["noise"] is None) or (
            isinstance(filt.fading, StrongTracking) and s["fading"] is None
        ):  # first step (or adaptation switched on later): fresh fading / noise states
            return filt.init(model, GaussianBelief(s["mean"], s["chol"]), k=s["step"] + 1)
        fs = self._filter_state()
        m = model.obs_dim
        for name, st, tensor in (
            ("strong tracking", fs.fading, None if fs.fading is None else fs.fading.V),
            ("the noise estimator", fs.noise, None if fs.noise is None else fs.noise.R),
        ):
            if st is not None and tensor.shape[-1] != m:
                raise ValueError(
                    f"{name} keeps statistics of a measurement of size {tensor.shape[-1]}, but "
                    f"this step has {m} measurement entries: use the same mini-batch size at "
                    "every step (e.g. drop the last incomplete batch)"
                )
        return fs

    def step(self, inputs=None, targets: Tensor | None = None) -> KalmanStep:
        """One filter step on a sample or a mini-batch (paper 003 Sec. IV, steps (2)-(3)).

        Args:
            inputs: module input (a sample or a mini-batch, module dtype and device), or a
                closure returning ``(inputs, targets)``.
            targets: ``module(inputs).shape``, module dtype and device, finite.
        Returns:
            :class:`KalmanStep` (loss, NIS, ``lambda_k``, log-likelihood, the engine's info).
            With one run, the posterior mean is written into the module's parameters.

        The step pre- and post-hooks of ``torch.optim`` (global and per optimiser) run as for
        any optimiser. Unlike ``torch.optim``'s own wrapper, the step is not wrapped in a
        profiler ``record_function`` scope: it made every tensor operation of a step slower
        (about 35 us, 10 %, of a 44-parameter SRUKF step on CPU). When the step needs no
        autograd (sigma-point filters; the EKF with a learner's closed-form Jacobian) it runs
        under ``torch.inference_mode()``, else under ``torch.no_grad()``; the tensors of the
        returned :class:`KalmanStep` may then be inference tensors (use them freely, but
        ``clone()`` one before using it in a computation tracked by autograd). The accessors
        :attr:`theta`, :attr:`belief`, :attr:`filter_state` and :meth:`parameter_covariance`
        return ordinary tensors.
        """
        args, kwargs = (self, inputs, targets), {}
        for hook in chain(
            _global_optimizer_pre_hooks.values(), self._optimizer_step_pre_hooks.values()
        ):
            result = hook(self, args, kwargs)
            if result is not None:
                if not (isinstance(result, tuple) and len(result) == 2):
                    raise RuntimeError(
                        "an optimizer step pre-hook must return None or (new_args, new_kwargs)"
                    )
                args, kwargs = result
        rest = list(args[1:3]) + [None] * max(0, 3 - len(args))
        inputs = kwargs.get("inputs", rest[0])
        targets = kwargs.get("targets", rest[1])
        if callable(inputs) and targets is None:
            pair = inputs()
            if not (isinstance(pair, tuple) and len(pair) == 2):
                raise TypeError("closure must return a pair (inputs, targets)")
            inputs, targets = pair
        if inputs is None:
            raise TypeError("step needs inputs and targets, or a closure returning them")
        with torch.inference_mode() if self._inference_ok(inputs) else torch.no_grad():
            out = self._step(inputs, targets)
        for hook in chain(
            self._optimizer_step_post_hooks.values(), _global_optimizer_post_hooks.values()
        ):
            hook(self, args, kwargs)
        return out

    # torch.optim wraps ``step`` of every Optimizer subclass in its profiling wrapper unless it is
    # marked as already wrapped; the hooks are run above instead
    step.hooked = True  # type: ignore[attr-defined]

    def _inference_ok(self, inputs) -> bool:
        """The step needs no autograd (sigma points, or the learner's closed-form Jacobian), so
        it runs under ``torch.inference_mode``: no version counters or view tracking, about
        50 us (15 %) less per 44-parameter step than ``no_grad``."""
        if not isinstance(self._filter.rule, Taylor):
            return True
        return self.param_groups[0]["jacobian"] == "auto" and self._closed_form_applies(inputs)

    def _closed_form_applies(self, inputs) -> bool:
        """The learner's closed-form Jacobian applies to these inputs (of one run, with
        per-run data)."""
        if self.per_run_data and isinstance(inputs, Tensor) and inputs.dim() > 0:
            inputs = inputs[0]
        return self.bridge.has_closed_form_jacobian(inputs, self._chunk)

    def _step(self, inputs: Tensor, targets: Tensor) -> KalmanStep:
        x, t, out_shape = self._check_batch(inputs, targets)
        model = self._model(x, out_shape)
        fstate = self._engine_state(model)
        if self.per_run_data:
            y = t.reshape(self.runs, -1).to(torch.float64)
        else:
            y = t.reshape(-1).to(torch.float64)
            if self.runs is not None:
                y = y.expand(self.runs, y.shape[0])
        s = self.state[_STATE_KEY]
        k = s["step"] + 1
        new, info = self._filter.step(model, fstate, y, None, k)
        self.state[_STATE_KEY] = {
            "mean": new.belief.mean,
            "chol": new.belief.chol,
            "fading": _dataclass_dict(new.fading),
            "noise": _dataclass_dict(new.noise),
            "step": k,
        }
        if self.runs is None:
            self.bridge.assign(new.belief.mean)
        loss = info.innovation.square().mean(-1)
        return KalmanStep(loss, info)

    # ------------------------------------------------------------------ persistence
    def load_state_dict(self, state_dict: dict) -> None:
        """Load a :meth:`state_dict`; the belief stays float64 (bit-identical resume).

        ``torch.optim`` casts per-parameter state to the parameter dtype; the belief is kept
        under the non-parameter key ``"kalman"``, copied here (never aliased), moved to the
        module's device, and rejected if any of its floating tensors is not float64 (a cast
        would have lost precision).
        """
        sd = dict(state_dict)
        st = dict(sd.get("state", {}))
        if _STATE_KEY not in st:
            raise ValueError(
                f"state_dict['state'] has no {_STATE_KEY!r} entry (not a KalmanOptimizer state)"
            )
        dev = self.bridge.device

        def conv(v, where):
            if isinstance(v, Tensor):
                if v.is_floating_point() and v.dtype != torch.float64:
                    raise ValueError(
                        f"state_dict {where} has dtype {v.dtype}; the Kalman belief must stay "
                        "float64 (it was cast, resuming would not be exact)"
                    )
                return v.detach().to(device=dev).clone()
            if isinstance(v, dict):
                return {kk: conv(vv, f"{where}[{kk!r}]") for kk, vv in v.items()}
            return v

        kal = conv(st[_STATE_KEY], f"['state'][{_STATE_KEY!r}]")
        groups = sd.get("param_groups", [{}])
        runs = groups[0].get("runs") if groups else None
        n = self.bridge.numel
        want = (n,) if runs is None else (runs, n)
        if tuple(kal["mean"].shape) != want or tuple(kal["chol"].shape) != want + (n,):
            raise ValueError(
                f"state_dict belief has mean {tuple(kal['mean'].shape)}, chol "
                f"{tuple(kal['chol'].shape)}; this optimiser needs {want} and {want + (n,)}"
            )
        st[_STATE_KEY] = kal
        sd["state"] = st
        super().load_state_dict(sd)
        self._setup()
        if self.runs is None:
            self.bridge.assign(self.state[_STATE_KEY]["mean"])


class EKF(KalmanOptimizer):
    """ANFIS-EKF style optimiser: :class:`KalmanOptimizer` with ``filter="ekf"``."""

    def __init__(self, params, module=None, **options) -> None:
        super().__init__(params, module, filter=options.pop("filter", "ekf"), **options)


class SRUKF(KalmanOptimizer):
    """Square-root UKF optimiser (paper 003 Eq. 10-30, Julier ``kappa = 1``)."""

    def __init__(self, params, module=None, **options) -> None:
        super().__init__(params, module, filter=options.pop("filter", "srukf"), **options)


class ImSRUKF(KalmanOptimizer):
    """ANFIS-ImSRUKF optimiser: SRUKF + Sage-Husa noise statistics (paper 003 Eq. 40-46)."""

    def __init__(self, params, module=None, **options) -> None:
        super().__init__(params, module, filter=options.pop("filter", "imsrukf"), **options)
