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

from collections.abc import Iterable
from itertools import chain

import torch
from torch import Tensor, nn
from torch.func import vmap
from torch.optim.optimizer import _global_optimizer_post_hooks, _global_optimizer_pre_hooks

from ..adapt.noise import NoiseEstimatorState
from ..adapt.strong_tracking import StrongTracking, StrongTrackingState
from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import check_flag, is_int
from ..filters.gaussian import FilterState, GaussianFilter, Taylor
from ._buffers import batch_statistics_only, explain_transform_error, tracking_batch_norms
from ._kalman_common import (
    OPTIMIZER_NOISE,
    KalmanStep,
    _call_closure,
    _check_matches,
    _check_targets,
    _checked_state_dict,
    _clone_state,
    _configure,
    _dataclass_dict,
    _Group,
    _group_bridge,
    _resolve_groups,
    _state_key,
    all_or_nothing_steps,
    noise_factor,
    norm_statistics,
    plain_option,
    restore_norm_statistics,
)
from ._step_model import step_model
from .compiled import compiled_steps
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


# ---------------------------------------------------------------------- the optimiser
#: the group options read when the optimiser is built or loaded (``lr`` is read at each step)
_FIXED_OPTIONS = ("filter", "P0", "Q", "R", "fading", "noise", "jacobian", "chunk_size")
#: the group options kept as Python numbers or tensors when given as NumPy numbers or arrays
#: (see ``plain_option``); arrays only for the covariances and ``lr`` (a tensor of one entry)
_PLAIN_OPTIONS = ("P0", "Q", "R", "lr", "fading", "chunk_size", "runs")
_ARRAY_OPTIONS = ("P0", "Q", "R", "lr")

# torch wraps Optimizer.add_param_group in _disable_dynamo, whose first call imports
# torch._dynamo (about 1.5 s of a command's start); a parameter group is never added inside a
# compiled region, so the method is called unwrapped
_BASE_ADD_PARAM_GROUP = getattr(
    torch.optim.Optimizer.add_param_group, "__wrapped__", torch.optim.Optimizer.add_param_group
)
# (state_dict and load_state_dict likewise: their first call cost a fresh process 1.5 s)
_BASE_STATE_DICT = getattr(
    torch.optim.Optimizer.state_dict, "__wrapped__", torch.optim.Optimizer.state_dict
)
_BASE_LOAD_STATE_DICT = getattr(
    torch.optim.Optimizer.load_state_dict, "__wrapped__", torch.optim.Optimizer.load_state_dict
)


def _group_record(group: dict) -> tuple:
    """What :meth:`KalmanOptimizer._check_options` compares a group with: its fixed options (the
    objects), copies of the tensor ones (an in-place change keeps the object), its parameters
    and their ``requires_grad``."""
    sources = {k: group[k] for k in _FIXED_OPTIONS if k in group}
    tensors = {k: v.detach().clone() for k, v in sources.items() if isinstance(v, Tensor)}
    params = tuple(group["params"])
    return sources, tensors, tuple(map(id, params)), tuple(p.requires_grad for p in params)


class KalmanOptimizer(torch.optim.Optimizer):
    """Train a module by Gaussian filtering of its parameters (paper 003 Eq. 44-46).

    Usage::

        opt = KalmanOptimizer(model, filter="imsrukf", P0=1.0, Q=1e-6, R=1e-3)
        for x, t in loader:
            opt.step(x, t)          # or opt.step(lambda: (x, t))

    Args:
        params: the module to train (its parameters with ``requires_grad=True`` form ``theta``),
            an iterable of some of its parameters, or an iterable of parameter groups (dicts with
            ``"params"`` and any of the options below, as in ``torch.optim``); with an iterable,
            ``module`` is required. As with ``torch.optim``, frozen parameters
            (``requires_grad=False``) in an iterable that also holds trainable ones are not
            trained (``module.parameters()`` of a model with frozen layers); an iterable of
            frozen parameters only trains them.
        module: the module, when ``params`` is an iterable.
        filter: a filter name of :func:`~prognos_torch.filters.variants.make_filter` (``"ekf"``,
            ``"srukf"``, ``"imsrukf"``, ``"ukf"``, ``"ckf"``, ``"sckf"``, ``"stekf"``, ``"stukf"``,
            ``"stsckf"``) or a configured :class:`GaussianFilter`.
        P0: prior covariance of ``theta_0``: scalar variance, ``(n,)`` variances, ``(n, n)``, or
            a dict ``{parameter name: variance}`` (:meth:`ParameterBridge.expand`).
        Q: random-walk covariance of Eq. 45 (as ``P0``; ``0`` allowed).
        R: measurement-noise covariance of ONE output vector (scalar, ``(n_out,)`` or
            ``(n_out, n_out)`` with ``n_out`` the last dimension of the model output); a mini-batch
            uses it block-diagonally.
        lr: learning rate, ``> 0`` (default 1): the filter uses the measurement noise ``R / lr``
            (see *Learning rate* below), so learning-rate schedulers work.
        fading: ``None`` (the filter's own setting), ``False`` (off), ``True``
            (``StrongTracking()``), a constant factor ``>= 1`` or a ``StrongTracking``.
        noise: ``None`` (the filter's own; for ``filter="imsrukf"`` :data:`OPTIMIZER_NOISE`),
            ``False`` (off), ``True`` (``SageHusa()``, all of paper 003 Eq. 40-43) or a
            ``SageHusa``/``MovingWindow``. A noise estimator or strong tracking needs a constant
            measurement size (same mini-batch size at every step).
        runs: ``None`` for one run, or ``R`` for ``R`` independent runs in one batch (one
            parameter group only).
        per_run_data: with ``runs=R``, every run gets its own data: ``step`` and ``predict``
            take inputs ``(R, *x)`` and targets ``(R, *out)`` (e.g. ``R`` noise realisations);
            default ``False``: all runs see the same inputs and targets.
        theta0: initial mean ``(n,)`` (or ``(R, n)`` with ``runs``; with several groups the
            groups' parameters one group after another); default: the module's current
            parameters (repeated over runs).
        jacobian: ``"auto"``, ``"rev"``, ``"fwd"`` or ``"autograd"``: how the EKF differentiates
            ``g`` (see :meth:`ParameterBridge.jacobian`; ``"auto"`` uses the learner's closed-form
            derivatives when it has them, as ELM and ANFIS do).
        chunk_size: vectorise at most this many parameter vectors / Jacobian products at once.

    ``filter``, ``P0``, ``Q``, ``R``, ``lr``, ``fading``, ``noise``, ``jacobian`` and
    ``chunk_size`` are per-group options (the arguments are the defaults); ``runs`` and
    ``per_run_data`` apply to the whole optimiser.

    Parameter groups. Every group has its own belief ``N(theta_g, P_g)``, its own filter and
    filter state: the joint belief is block-diagonal, the groups a priori independent. A step
    updates the groups one after another on the same mini-batch, each by one engine step of its
    own filter in which the other groups are held at their current means (those earlier in
    ``param_groups`` already updated in this step): block-coordinate filtering in Gauss-Seidel
    order. The cross-covariances between groups are not kept, as in decoupled EKF training
    (Puskorius and Feldkamp, 1991), but each group has its own innovation covariance (its own
    ``R``). So an optimiser with groups ``A`` and ``B`` is exactly two single-group optimisers
    on ``A`` and on ``B`` stepped in that order (``tests/test_optim_groups.py``); the cost is one
    ``n_g``-dimensional filter step per group instead of one ``n``-dimensional one.
    :meth:`add_param_group` adds a group whose belief starts at the module's current values
    with its ``P0``. Parameters written outside the optimiser between steps (weights loaded
    into the module, a manual edit) become the belief's mean at the next step, with its
    covariance kept, as a ``torch.optim`` optimiser continues from them. :attr:`theta`,
    :attr:`belief`, :meth:`parameter_covariance` and :meth:`parameter_std` list the groups one
    after another (block-diagonal); per group:
    :attr:`beliefs`, :attr:`filters`, :attr:`filter_states`.

    Learning rate. ``lr`` is the learning rate ``eta`` of EKF training (Puskorius and Feldkamp:
    the measurement noise ``R = eta^-1 I``): the filter uses ``R / lr``. With a small gain
    (``H P H^T << R``) the update ``K e = lr P H^T R^-1 e`` is proportional to ``lr``, like a
    gradient step; a larger ``lr`` trusts the targets more. ``torch.optim.lr_scheduler``
    schedulers (``StepLR``, ``ExponentialLR``, ``LambdaLR``, ...) therefore anneal the
    measurement noise; they read and write ``param_groups[i]["lr"]`` and the next step uses it.
    A group whose filter estimates ``R`` itself (``"imsrukf"``, a ``SageHusa`` or
    ``MovingWindow`` with ``"R"`` in ``estimate``) refuses ``lr != 1`` with a ``ValueError``.

    Buffers. A BatchNorm layer in training mode normalises by the batch statistics in every
    evaluation of the filter, and its running statistics are updated once per step, by one
    forward pass of the mini-batch at the parameters before the step, as in a ``torch.optim``
    training loop (:mod:`prognos_torch.optim._buffers`; not with ``runs``: the runs would share
    one set of statistics). In ``eval()`` mode it uses its running statistics. Other layers that
    change buffers in ``forward``, or draw random numbers (Dropout in training mode), are
    refused with a ``ValueError`` saying so.

    Closures. ``step(closure)`` accepts a closure returning ``(inputs, targets)``. A closure
    returning a loss, as ``LBFGS`` takes, is refused with a ``TypeError``: a Kalman filter
    updates ``theta`` from the model outputs and the targets (Eq. 46), which one loss value
    does not carry.

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
    per step). Pass ``noise=SageHusa()`` for the paper's full estimator (on Lorenz: mean test
    MAE 0.99, max 1.59 over 10 initialisations; on the 3-8-1 MLP below the MSE diverges to
    2-45). While ``P`` is being learned, ``e e^T`` is mostly smaller than ``H P H^T``, so the
    ``R`` of Eq. 43 as printed is mostly negative and held at the projection's floor
    (``1e-6 R_0``): every mini-batch is fitted exactly, and with ``d_1 = 1`` the prior ``Q_0``
    is replaced at the first step by that step's rank-one term (``Q`` grew from 1e-6 to 0.07).
    So ``R`` is estimated in the post-fit form (:class:`SageHusa`, ``r_form="post-fit"``:
    positive semi-definite by construction; on the MLP it recovers the true noise variance,
    0.0105 against 0.01) and the prior counts as 299 earlier steps (``k0 = 300``). ``k0`` was
    chosen on a 3-8-1 tanh MLP (batches of 8, ``P0 = 1``, ``Q = 1e-6``, ``R = 1e-2``, 6 epochs,
    ``tests/test_sage_husa_fidelity.py``) from {1, 10, 41, 100, 300, 1000}: MSE over seeds 0-2
    0.015-0.062 (k0 = 1), 0.015-0.038 (41), 0.016-0.023 (100), 0.013-0.015 (300),
    0.012-0.013 (1000), SRUKF 0.010-0.011; 300 is the smallest within 1.5x of SRUKF (1000
    nearly freezes ``Q``). Checked on Lorenz, not tuned there (10 initialisations, one pass):
    mean test MAE 0.0013 +- 0.0002 (max 0.0018), against 0.0031 +- 0.0014 (max 0.0066) with
    Eq. 43 as printed and ``k0 = 1``, and SRUKF's 0.0012.
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
        lr: float = 1.0,
        fading=None,
        noise=None,
        runs: int | None = None,
        per_run_data: bool = False,
        theta0: Tensor | None = None,
        jacobian: str = "auto",
        chunk_size: int | None = None,
    ) -> None:
        module, groups = _resolve_groups(params, module)
        runs = plain_option(runs, arrays=False)
        if runs is not None and (not is_int(runs) or runs < 1):
            raise ValueError(f"runs must be None or a positive int, got {runs!r}")
        per_run_data = check_flag(per_run_data, "per_run_data")  # (numpy.bool_ was refused)
        if per_run_data and runs is None:
            raise ValueError("per_run_data=True needs runs=R (the number of runs)")
        defaults = dict(
            filter=filter,
            P0=plain_option(P0),  # (NumPy numbers and arrays as Python numbers and tensors)
            Q=plain_option(Q),
            R=plain_option(R),
            lr=plain_option(lr),
            fading=plain_option(fading, arrays=False),
            noise=noise,
            runs=runs,
            per_run_data=per_run_data,
            jacobian=jacobian,
            chunk_size=plain_option(chunk_size, arrays=False),
        )
        self.module = module
        self._cfg: list[_Group] | None = []
        self._building = True
        super().__init__(groups, defaults)
        self._building = False
        self._setup()
        parts = self._split_theta0(theta0)
        for i in range(len(self.param_groups)):
            self.state[_state_key(i)] = self._initial_state(i, parts[i])

    def __getstate__(self) -> dict:
        # torch.optim keeps only defaults, state and param_groups; copy.deepcopy and pickle of
        # a Kalman optimiser also need its module and bridges. The per-group configuration
        # (filters, noise factors, per-shape step models that close over this optimiser) is
        # rebuilt by the copy from its own param_groups.
        state = self.__dict__.copy()
        state["_cfg"], state["_inputs"], state["_out_shapes"] = None, [None], {}
        return state

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        if self.__dict__.get("_cfg") is None and "module" in self.__dict__:
            self._setup()

    def add_param_group(self, param_group: dict) -> None:
        """Add a parameter group (a dict with ``"params"``, parameters of :attr:`module`, and
        any per-group option); its belief starts at the parameters' current values with its
        ``P0`` (repeated over runs)."""
        if not isinstance(param_group, dict):
            raise TypeError(f"param_group must be a dict, got {type(param_group)}")
        if "params" not in param_group:
            raise ValueError("param_group must have a 'params' entry (parameters of the module)")
        group = {
            k: plain_option(v, arrays=k in _ARRAY_OPTIONS) if k in _PLAIN_OPTIONS else v
            for k, v in param_group.items()
        }
        for key in ("runs", "per_run_data"):
            if key in group and group[key] != self.defaults[key]:
                raise ValueError(
                    f"{key} applies to the whole optimiser ({self.defaults[key]!r}), not to one "
                    f"parameter group (got {group[key]!r})"
                )
        if self.param_groups and self.defaults["runs"] is not None:
            raise ValueError(
                "several parameter groups need runs=None: with runs=R the module does not hold "
                "the runs' parameters that the other groups would be evaluated at; use one group "
                "with per-parameter P0 and Q ({name: variance} dicts)"
            )
        group["params"] = _group_bridge(self.module, group["params"]).parameters()
        cfg = _configure(
            self.module, {**self.defaults, **group}, f"param_groups[{len(self.param_groups)}]"
        )
        _BASE_ADD_PARAM_GROUP(self, group)  # (super().add_param_group, without the import)
        if not self._building:
            i = len(self.param_groups) - 1
            self._cfg.append(cfg)
            self._records.append(_group_record(self.param_groups[i]))
            self._union()
            self.state[_state_key(i)] = self._initial_state(i, None)

    # ------------------------------------------------------------------ configuration

    def _setup(self) -> None:
        """Derive every group's filter and noise factors from ``param_groups`` (also after a
        load or a copy)."""
        self._cfg = [
            _configure(self.module, g, f"param_groups[{i}]")
            for i, g in enumerate(self.param_groups)
        ]
        self._records = [_group_record(g) for g in self.param_groups]
        self._union()
        self._out_shapes: dict[tuple, torch.Size] = {}
        self._inputs: list = [None]

    def _union(self) -> None:
        """The bridge over all groups' parameters and the map from group order to its order."""
        names = [n for c in self._cfg for n in c.bridge.names]
        self.bridge = (
            self._cfg[0].bridge if len(self._cfg) == 1 else ParameterBridge(self.module, names)
        )
        if len(self._cfg) == 1:
            self._order = None
            return
        start, where = 0, {}
        for c in self._cfg:
            for name, k in zip(c.bridge.names, c.bridge.numels):
                where[name] = (start, start + k)
                start += k
        self._order = torch.cat(
            [torch.arange(*where[name], device=self.bridge.device) for name in self.bridge.names]
        )

    def _split_theta0(self, theta0) -> list[Tensor | None]:
        if theta0 is None:
            return [None] * len(self._cfg)
        if not isinstance(theta0, Tensor):
            raise TypeError("theta0 must be a torch.Tensor")
        runs, n = self.runs, sum(c.bridge.numel for c in self._cfg)
        want = (n,) if runs is None else (runs, n)
        if tuple(theta0.shape) != want:
            raise ValueError(f"theta0 must have shape {want}, got {tuple(theta0.shape)}")
        if theta0.device != self.bridge.device:
            raise ValueError(f"theta0 is on {theta0.device}, the module on {self.bridge.device}")
        if not bool(torch.isfinite(theta0).all()):
            raise ValueError("theta0 contains non-finite values")
        theta0 = theta0.detach().to(torch.float64)
        return list(theta0.split([c.bridge.numel for c in self._cfg], dim=-1))

    def _initial_state(self, i: int, theta0: Tensor | None) -> dict:
        cfg, runs = self._cfg[i], self.runs
        n = cfg.bridge.numel
        if theta0 is None:
            mean = cfg.bridge.flatten()
            if runs is not None:
                mean = mean.expand(runs, n).clone()
        else:
            mean = theta0.clone()
        chol = cfg.chol_P0.expand(*mean.shape[:-1], n, n).clone()
        if runs is None:
            cfg.bridge.assign(mean)
        return {"mean": mean, "chol": chol, "fading": None, "noise": None, "step": 0}

    @property
    def runs(self) -> int | None:
        return self.param_groups[0]["runs"]

    def _single(self, what: str, plural: str) -> None:
        if len(self._cfg) != 1:
            raise ValueError(
                f"{what} is ambiguous with {len(self._cfg)} parameter groups: use {plural} "
                "(one per group)"
            )

    @property
    def filter(self) -> GaussianFilter:
        """The configured engine filter (one parameter group; else see :attr:`filters`)."""
        self._single("filter", "filters")
        return self._cfg[0].filter

    @property
    def filters(self) -> tuple[GaussianFilter, ...]:
        """The configured engine filter of every parameter group."""
        return tuple(c.filter for c in self._cfg)

    # ------------------------------------------------------------------ belief access
    def _means(self) -> list[Tensor]:
        return [self.state[_state_key(i)]["mean"] for i in range(len(self._cfg))]

    def _chols(self) -> list[Tensor]:
        return [self.state[_state_key(i)]["chol"] for i in range(len(self._cfg))]

    def _union_mean(self) -> Tensor:
        """The posterior mean in :attr:`bridge` order (the module's order of parameters)."""
        means = self._means()
        if self._order is None:
            return means[0]
        return torch.cat(means, -1)[..., self._order]

    @property
    def theta(self) -> Tensor:
        """Posterior mean of ``theta``: ``(n,)`` or ``(R, n)``, float64 (a copy; several
        groups one after another)."""
        return torch.cat(self._means(), -1).clone()

    @property
    def belief(self) -> GaussianBelief:
        """The current float64 belief ``N(theta, P)`` over the parameters (a copy; with several
        groups block-diagonal, groups one after another)."""
        means, chols = self._means(), self._chols()
        if len(chols) == 1:
            return GaussianBelief(means[0].clone(), chols[0].clone())
        return GaussianBelief(torch.cat(means, -1), torch.block_diag(*chols))

    @property
    def beliefs(self) -> tuple[GaussianBelief, ...]:
        """The belief of every parameter group (copies)."""
        return tuple(
            GaussianBelief(m.clone(), S.clone()) for m, S in zip(self._means(), self._chols())
        )

    @property
    def filter_state(self) -> FilterState:
        """The engine's :class:`FilterState` (belief, fading and noise-estimator states; a
        copy; one parameter group, else see :attr:`filter_states`)."""
        self._single("filter_state", "filter_states")
        return self.filter_states[0]

    @property
    def filter_states(self) -> tuple[FilterState, ...]:
        """The engine's :class:`FilterState` of every parameter group (copies)."""
        out = []
        for i in range(len(self._cfg)):
            fs = self._filter_state(i)
            out.append(
                FilterState(
                    GaussianBelief(fs.belief.mean.clone(), fs.belief.chol.clone()),
                    _clone_state(fs.fading),
                    _clone_state(fs.noise),
                )
            )
        return tuple(out)

    def _filter_state(self, i: int) -> FilterState:
        s = self.state[_state_key(i)]
        fst = None if s["fading"] is None else StrongTrackingState(**s["fading"])
        nst = None if s["noise"] is None else NoiseEstimatorState(**s["noise"])
        return FilterState(GaussianBelief(s["mean"], s["chol"]), fst, nst)

    def parameter_covariance(self) -> Tensor:
        """Posterior covariance of ``theta``: ``(n, n)`` or ``(R, n, n)`` float64
        (block-diagonal with several groups)."""
        covs = [S @ S.mT for S in self._chols()]
        return covs[0] if len(covs) == 1 else torch.block_diag(*covs)

    def parameter_std(self) -> Tensor:
        """Posterior standard deviations of ``theta``: ``(n,)`` or ``(R, n)`` float64."""
        return torch.cat([S.square().sum(-1).sqrt() for S in self._chols()], -1)

    @torch.no_grad()
    def predict(self, inputs: Tensor) -> Tensor:
        """Model outputs at the posterior mean: ``module(inputs)`` for one run, ``(R, *out)``
        with ``runs=R`` (module dtype). With ``per_run_data``, ``inputs`` is ``(R, *x)``.
        BatchNorm layers in training mode use the batch statistics and keep their running
        statistics (``predict`` changes nothing)."""
        x = self._check_inputs(inputs)
        mean, b, chunk = self._union_mean(), self.bridge, self._chunk
        with batch_statistics_only(tracking_batch_norms(self.module)):
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

    def _check_inputs(self, inputs, checked: bool = False) -> Tensor:
        b = self.bridge
        if not isinstance(inputs, Tensor):
            raise TypeError(f"inputs must be a torch.Tensor, got {type(inputs)}")
        _check_matches(inputs, "inputs", b.dtype, b.device, checked)
        if inputs.numel() == 0:  # (it surfaced as "obs_dim must be a positive int, got 0")
            raise ValueError(
                f"inputs hold no sample (shape {tuple(inputs.shape)}): a step needs one"
            )
        if self.per_run_data and (inputs.dim() < 1 or inputs.shape[0] != self.runs):
            raise ValueError(
                f"inputs must have shape (runs={self.runs}, ...) with per_run_data=True, got "
                f"{tuple(inputs.shape)}"
            )
        return inputs

    def _check_batch(self, inputs, targets, checked: bool = False):
        """``(inputs, targets, output shape of one run, any target missing)``, validated (the
        values only when not ``checked`` already: finite inputs, targets finite or NaN where
        missing)."""
        b = self.bridge
        x = self._check_inputs(inputs, checked)
        per_run = self.per_run_data
        key = tuple(x.shape)
        out_shape = self._out_shapes.get(key)
        if out_shape is None:  # the output of one run (per-run data: for its own inputs)
            theta = self._union_mean().reshape(-1, b.numel)[0]
            out = b.functional(theta, x[0] if per_run else x)
            if not isinstance(out, Tensor):
                raise TypeError(
                    f"the module must return one tensor (the measurement y), got "
                    f"{type(out).__name__}; concatenate several outputs into one"
                )
            out_shape = out.shape
            self._out_shapes[key] = out_shape
        want = ((self.runs,) if per_run else ()) + tuple(out_shape)
        if not isinstance(targets, Tensor):
            raise TypeError(f"targets must be a torch.Tensor of shape {want}")
        if tuple(targets.shape) != want:
            raise ValueError(
                f"targets must have shape {want} (the model output for inputs of "
                f"shape {tuple(x.shape)}), got {tuple(targets.shape)}"
            )
        if checked:
            _check_matches(targets, "targets", b.dtype, b.device, True)
            return x, targets, out_shape, False
        return x, targets, out_shape, _check_targets(targets, b.dtype, b.device)

    def _engine_state(self, i: int, model: StateSpaceModel) -> FilterState:
        s = self.state[_state_key(i)]
        filt = self._cfg[i].filter
        if (filt.noise is not None and s["noise"] is None) or (
            isinstance(filt.fading, StrongTracking) and s["fading"] is None
        ):  # first step (or adaptation switched on later): fresh fading / noise states
            return filt.init(model, GaussianBelief(s["mean"], s["chol"]), k=s["step"] + 1)
        fs = self._filter_state(i)
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

    def step(self, inputs=None, targets: Tensor | None = None, *, closure=None) -> KalmanStep:
        """One filter step on a sample or a mini-batch (paper 003 Sec. IV, steps (2)-(3)).

        Args:
            inputs: module input (a sample or a mini-batch, module dtype and device), or a
                closure returning ``(inputs, targets)``.
            targets: ``module(inputs).shape``, module dtype and device, finite.
            closure: a closure returning ``(inputs, targets)`` (the keyword form of passing it
                as ``inputs``). A closure returning a loss is refused (see the class notes).
        Returns:
            :class:`KalmanStep` (loss, NIS, ``lambda_k``, log-likelihood, the engine's info of
            every group). With one run, the posterior means are written into the module's
            parameters.
        Raises:
            ValueError: the update gave a non-finite mean or factor (the module's output or
                Jacobian is NaN or inf at the current parameters for these inputs); every
                group's belief and the module's parameters stay as before the step.

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
        args, kwargs = (self, inputs, targets), ({} if closure is None else {"closure": closure})
        changed = False
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
                changed = True
        rest = list(args[1:3]) + [None] * max(0, 3 - len(args))
        inputs = kwargs.get("inputs", rest[0])
        targets = kwargs.get("targets", rest[1])
        closure = kwargs.get("closure")
        if closure is not None:
            if inputs is not None or targets is not None:
                raise TypeError("step takes inputs and targets, or a closure, not both")
            inputs = closure
        if callable(inputs) and targets is None:
            inputs, targets = _call_closure(inputs)
            changed = True
        if inputs is None:
            raise TypeError("step needs inputs and targets, or a closure returning them")
        # the values were checked finite by fit (once per call) unless a hook or a closure
        # supplied them
        checked = self._finite_checked and not changed
        with torch.inference_mode() if self._inference_ok(inputs) else torch.no_grad():
            out = self._step(inputs, targets, checked)
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
        for cfg, g in zip(self._cfg, self.param_groups):
            if isinstance(cfg.filter.rule, Taylor) and not (
                g["jacobian"] == "auto"
                and self._closed_form_applies(cfg.bridge, inputs, g["chunk_size"])
            ):
                return False
        return True

    def _closed_form_applies(self, bridge: ParameterBridge, inputs, chunk) -> bool:
        """The learner's closed-form Jacobian applies to these inputs (of one run, with
        per-run data)."""
        if self.per_run_data and isinstance(inputs, Tensor) and inputs.dim() > 0:
            inputs = inputs[0]
        return bridge.has_closed_form_jacobian(inputs, chunk)

    #: set by :func:`~prognos_torch.optim.fit` while it steps through data it has checked to
    #: be finite (once per call); a step then checks types, shapes, dtypes and devices only
    _finite_checked = False
    #: seconds the last :meth:`steps` call spent compiling
    compile_time = 0.0

    def _check_options(self) -> None:
        """Options other than ``lr`` are read when the optimiser is built or loaded: a later
        change in ``param_groups`` (a new value, a tensor changed in place, other
        ``params``) or a parameter frozen or unfrozen since is refused rather than ignored (and
        then applied by a reload, so that a resumed run would differ)."""
        for i, (g, rec) in enumerate(zip(self.param_groups, self._records)):
            src, tensors, ids, grads = rec
            for key, value in src.items():
                if g.get(key) is not value or (
                    key in tensors and not torch.equal(value.detach(), tensors[key])
                ):
                    raise ValueError(
                        f"param_groups[{i}][{key!r}] changed after the optimiser was built; "
                        "options other than 'lr' are read when it is built or loaded "
                        "(load_state_dict): build a new optimiser to change them"
                    )
            params = g["params"]
            if tuple(map(id, params)) != ids:
                raise ValueError(
                    f"param_groups[{i}]['params'] changed after the optimiser was built; its "
                    "parameters are the filter's state: build a new optimiser (or "
                    "add_param_group) to train others"
                )
            if tuple(p.requires_grad for p in params) != grads:
                raise ValueError(
                    f"a parameter of param_groups[{i}] was frozen or unfrozen (requires_grad) "
                    "after the optimiser was built; its parameters are the filter's state: "
                    "build a new optimiser over the parameters to train"
                )

    def _adopt_module_writes(self) -> None:
        """Parameters written outside the optimiser since its last step (weights loaded into the
        module, a manual edit) become the filter's mean, as a ``torch.optim`` optimiser would
        continue from them; the covariance and the adaptive states are kept. A rewrite with the
        same values (the module's own state reloaded) keeps the float64 mean."""
        if self.runs is not None:
            return
        for i, cfg in enumerate(self._cfg):
            # by value: a write through .data moves no version counter
            b = cfg.bridge
            s = self.state[_state_key(i)]
            theta = b.flatten()
            if not torch.equal(theta, s["mean"].to(b.dtype).to(torch.float64)):
                s["mean"] = theta

    def _before_steps(self) -> None:
        """What a step (or a compiled sequence of steps) checks and adopts first."""
        self._check_options()
        self._adopt_module_writes()

    def _step(self, inputs: Tensor, targets: Tensor, checked: bool = False) -> KalmanStep:
        self._before_steps()
        norms = tracking_batch_norms(self.module)
        with batch_statistics_only(norms):
            x, t, out_shape, any_missing = self._check_batch(inputs, targets, checked)
        stats = None
        if norms:
            if self.runs is not None:
                raise ValueError(
                    "the module has BatchNorm layers in training mode, whose running statistics "
                    "the runs would share: call module.eval() (fixed statistics) or use runs=None"
                )
            stats = norm_statistics(norms)  # put back if the step fails
            self.module(x)  # running statistics: once, at the parameters before the step
        if t.dtype != torch.float64:
            t = t.to(torch.float64)
        if self.per_run_data:
            y = t.reshape(self.runs, -1)
        else:
            y = t.reshape(-1)
            if self.runs is not None:
                y = y.expand(self.runs, y.shape[0])
        if any_missing:
            self._check_partial(y)
        infos, before = [], {}
        try:  # all or nothing: a group that fails puts back the groups updated before it
            with batch_statistics_only(norms):
                for i, cfg in enumerate(self._cfg):
                    model = step_model(self, i, x, out_shape)
                    fstate = self._engine_state(i, model)
                    key = _state_key(i)
                    k = self.state[key]["step"] + 1
                    try:  # y checked (finite, NaN where missing): the engine's checks not repeated
                        new, info = cfg.filter._update(model, fstate, y, None, k, any_missing)
                    except RuntimeError as exc:
                        clear = explain_transform_error(exc)
                        if clear is None:
                            raise
                        raise clear from exc
                    if not (bool(torch.isfinite(new.belief.mean).all())
                            and bool(torch.isfinite(new.belief.chol).all())):  # fmt: skip
                        raise ValueError(
                            f"the step gave a non-finite estimate of parameter group {i}: the "
                            "module's output (or its Jacobian) at the current parameters is NaN "
                            "or inf for these inputs; the belief and the parameters are left as "
                            "they were before the step"
                        )
                    before[i] = self.state[key]
                    self.state[key] = {
                        "mean": new.belief.mean,
                        "chol": new.belief.chol,
                        "fading": _dataclass_dict(new.fading),
                        "noise": _dataclass_dict(new.noise),
                        "step": k,
                    }
                    if self.runs is None:
                        cfg.bridge.assign(new.belief.mean)
                    infos.append(info)
        except BaseException:
            self._restore(before)
            if stats is not None:
                restore_norm_statistics(norms, stats)
            raise
        e2 = infos[0].innovation.square()  # (the engine's innovation is 0 where y is missing)
        if any_missing:  # the mean over the observed entries (NaN where none is observed)
            loss = e2.sum(-1) / (~torch.isnan(y)).sum(-1)
        else:
            loss = e2.mean(-1)
        return KalmanStep(loss, infos[0], tuple(infos))

    def _restore(self, before: dict) -> None:
        """Put back the states (and the module's parameters) of the groups a failed step
        had updated (``before``: group index -> its former state)."""
        for i, st in before.items():
            self.state[_state_key(i)] = st
            if self.runs is None:
                self._cfg[i].bridge.assign(st["mean"])

    def _check_partial(self, y: Tensor) -> None:
        """A robust filter (paper 004's bound) updates with whole measurement vectors only: a
        mini-batch with some targets missing would be skipped whole, so it is refused."""
        if all(cfg.filter.robust is None for cfg in self._cfg):
            return
        nan = torch.isnan(y)
        if bool((nan.any(-1) & ~nan.all(-1)).any()):
            raise ValueError(
                "targets contain NaN (missing) beside observed ones, and the robust filter "
                "updates with whole mini-batches only (the engine's robust bound): it would "
                "skip this one whole; drop the missing samples, or use a filter without the "
                "robust bound"
            )

    # ------------------------------------------------------------------ a sequence of steps
    def steps(self, inputs: Tensor, targets: Tensor, *, compile: bool = False) -> Tensor:
        """``T`` steps on a sequence of mini-batches, in order: ``step(inputs[t], targets[t])``.

        Args:
            inputs: ``(T, *x)``, one mini-batch per row (module dtype and device, finite).
            targets: ``(T, *out)`` with ``out`` the model output for one mini-batch.
            compile: run the ``T`` steps as ONE ``torch.compile(fullgraph=True)`` call, the
                loop a traced ``scan`` (:func:`~prognos_torch.filters.scan` with
                ``compile=True``) over the same engine step (:meth:`GaussianFilter.step`): the
                same numbers as eager steps up to rounding (float64: ``<= 1e-12``). The
                first call per mini-batch shape compiles (tens of seconds on CPU); later calls
                reuse the code. Needs one parameter group, no per-run data, a filter without
                adaptation state (no strong tracking, no noise estimator, no robust bound), a
                module without tracking BatchNorm layers, and for the EKF the learner's
                closed-form Jacobian.
        Returns:
            ``(T,)`` (or ``(T, R)`` with ``runs=R``) the loss of every step, as
            :attr:`KalmanStep.loss`.

        :attr:`compile_time` is set to the seconds this call spent compiling (0 when the
        compiled code was reused); that first, compiling run is discarded and the pass run
        again, so the call's time minus :attr:`compile_time` is the time of one pass.

        The step hooks of ``torch.optim`` run once around the whole sequence when compiled
        (with ``args = (self, inputs, targets)``), at every step when not. All or nothing: a
        failing row raises naming it, and the steps before it are undone.
        """
        if not isinstance(inputs, Tensor) or not isinstance(targets, Tensor):
            raise TypeError("steps needs tensors inputs (T, *x) and targets (T, *out)")
        if inputs.dim() < 1 or targets.dim() < 1 or inputs.shape[0] != targets.shape[0]:
            raise ValueError(
                f"inputs and targets must have one row per step (T, ...), got "
                f"{tuple(inputs.shape)} and {tuple(targets.shape)}"
            )
        self.compile_time = 0.0
        if not compile:
            return all_or_nothing_steps(self, inputs, targets)
        self._before_steps()
        return compiled_steps(self, inputs, targets)

    def _steps_eager_from(self, s: dict, inputs: Tensor, targets: Tensor) -> Tensor:
        """The eager steps from the state ``s`` (the compiled pass is discarded)."""
        self.state[_state_key(0)] = s
        return all_or_nothing_steps(self, inputs, targets)

    # ------------------------------------------------------------------ persistence
    def state_dict(self) -> dict:
        """``torch.optim``'s state dict; each group's belief entry also holds the ``shapes`` of
        its parameters, which :meth:`load_state_dict` compares."""
        sd = _BASE_STATE_DICT(self)  # (super().state_dict(), without the import)
        for i, cfg in enumerate(self._cfg):
            key = _state_key(i)
            if key in sd["state"]:  # (a copy: the entry is the live state's dict)
                shapes = [list(v) for v in cfg.bridge.shapes]
                sd["state"][key] = dict(sd["state"][key], shapes=shapes)
        return sd

    def load_state_dict(self, state_dict: dict) -> None:
        """Load a :meth:`state_dict`; the beliefs stay float64 (bit-identical resume).

        ``torch.optim`` casts per-parameter state to the parameter dtype; the belief of group
        ``i`` is kept under the non-parameter key ``"kalman"`` (``"kalman.i"`` for ``i > 0``),
        copied here (never aliased), moved to the module's device, and rejected if any of its
        floating tensors is not float64 (a cast would have lost precision). A state dict
        without ``lr`` (written before the option existed) loads with ``lr = 1``.
        """
        sd = _checked_state_dict(state_dict, self.module, self.param_groups, self.bridge.device)
        _BASE_LOAD_STATE_DICT(self, sd)  # (super().load_state_dict(), without the import)
        self._setup()
        if self.runs is None:
            for i, cfg in enumerate(self._cfg):
                cfg.bridge.assign(self.state[_state_key(i)]["mean"])


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
