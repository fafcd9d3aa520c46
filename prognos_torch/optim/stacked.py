"""R runs of one learner as one predictor (Monte Carlo runs batched through a run axis).

A Monte Carlo study trains the same learner ``R`` times (own initialisation, own data or own
optimiser) and then feeds all runs through one batched filter. :class:`StackedLearner` holds
the ``R`` parameter sets of one structure and evaluates run ``r``'s inputs with run ``r``'s
parameters, the run axis at a fixed position of the input:

* evaluation by ``torch.func.vmap`` of ``functional_call`` (any module), or by the learner's own
  parameter-batched ``forward_with`` (``evaluate="broadcast"``: every parameter set on every
  run's inputs, the run's own block kept; ``R`` times the arithmetic in one pass, which is
  faster for a few runs of a small learner);
* optionally per-run min-max scaling: a learner trained on its run's data scaled to ``[0, 1]``
  used on raw values, ``y = lo + (hi - lo) f((x - lo) / (hi - lo))``;
* ``trainable=True`` registers the stacked parameters as ``nn.Parameter``: one gradient
  optimiser trains the ``R`` runs at once with :func:`run_sum_mse` (Adam is element-wise and the
  loss separates over runs, so this equals ``R`` independent runs on the same mini-batches);
* :func:`fit_together` (one gradient optimiser over the stack) and :func:`fit_kalman_runs`
  (one :class:`~prognos_torch.optim.KalmanOptimizer` with ``runs=R`` where the runs share every
  tensor outside the Kalman state, one optimiser per run otherwise) train ``R`` modules on the
  same data and return their stack;
* :meth:`~StackedLearner.input_gradient` for
  :func:`~prognos_torch.prognosis.learner_transition_model` (``jacobian="input_gradient"``),
  :meth:`~StackedLearner.select` for a subset of runs (e.g. the runs that did not diverge).

:class:`StackedForecaster` does the same for measurement forecasters whose learners carry an
online state (ROS-ELM, paper 000 Eq. 54-56): the ``R`` runs x ``C`` channels are packed into one
forecaster with ``R C`` channels, so that every run keeps its own hidden layers while the
filters stay batched over runs.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn
from torch.func import functional_call, vmap

from ..core.validation import check_pos_int, is_int
from .fit import _check_data, fit
from .kalman import KalmanOptimizer
from .params import ParameterBridge, Selector

__all__ = [
    "StackedLearner",
    "StackedForecaster",
    "run_sum_mse",
    "fit_together",
    "fit_kalman_runs",
    "kalman_runs_optimizer",
]

EVALUATE = ("vmap", "broadcast")


def run_sum_mse(pred: Tensor, target: Tensor) -> Tensor:
    """Sum over runs of each run's mean squared error, samples along dim 0.

    With ``pred`` and ``target`` ``(B, R, ...)`` (the layout of a :class:`StackedLearner` with
    ``run_dim=1``), ``sum_r mean_b (pred - target)^2``: its gradient for run ``r``'s parameters
    is that run's own mean-squared-error gradient. NaN targets (missing) are left out of the
    means (:func:`~prognos_torch.optim.fit` accepts it with missing targets).
    """
    obs = ~torch.isnan(target)
    if bool(obs.all()):
        return (pred - target).square().mean(0).sum()
    d = torch.where(obs, pred - target, 0.0)
    return (d.square().sum(0) / obs.sum(0).clamp(min=1)).sum()


run_sum_mse.handles_missing = True  # type: ignore[attr-defined]


def _index(index, runs: int) -> Tensor | slice:
    if isinstance(index, slice):
        return index
    if is_int(index):
        index = int(index)
        if not -runs <= index < runs:  # (a slice past the end picked no run, silently)
            raise IndexError(f"run index {index} is out of range for {runs} runs")
        return slice(index, index + 1 if index != -1 else None)
    idx = torch.as_tensor(index)
    if idx.dtype == torch.bool:
        if idx.shape != (runs,):
            raise ValueError(f"a boolean run mask must have shape ({runs},), got {idx.shape}")
        return idx.nonzero().flatten()
    if idx.dim() == 1 and idx.numel() == 0:  # ([] is a float tensor: it was refused)
        return idx.long()
    if idx.dim() != 1 or idx.dtype not in (torch.int32, torch.int64):
        raise TypeError("index must be a slice, an int, a (runs,) bool mask or a 1-D int index")
    out = (idx < -runs) | (idx >= runs)
    if bool(out.any()):  # (torch's IndexError named neither the runs nor the index)
        bad = int(idx[out][0])
        raise IndexError(f"run index {bad} is out of range for {runs} runs")
    return idx


class StackedLearner(nn.Module):
    """``R`` parameter sets of one learner structure evaluated as one predictor.

    Args:
        base: the learner (an ``nn.Module`` with ``forward(x) (..., n_in) -> (..., n_out)``);
            it supplies the structure and every tensor not in ``params``. Kept outside the
            module's own parameters.
        params: ``{name: (R, *shape)}`` per-run values of ``base``'s parameters (a subset is
            fine: the others are shared by all runs).
        run_dim: position of the run axis in the input (and output); ``0`` (runs leading) or
            ``1`` (samples leading, e.g. for :func:`~prognos_torch.optim.fit`).
        evaluate: ``"vmap"`` (default) or ``"broadcast"`` (the base's ``forward_with``, see the
            module notes; inputs ``(R, n_in)`` or ``(R, B, n_in)``, ``run_dim=0``).
        lo, hi: optional ``(R,)`` per-run scaling bounds: inputs are mapped to
            ``(x - lo) / (hi - lo)`` and outputs back.
        trainable: register the per-run values of the base's trainable parameters as
            ``nn.Parameter`` (the others as buffers); default: all as buffers (a trained
            predictor).

    Call: ``x`` with ``R`` along ``run_dim`` and the input features last, any other dims
    between; returns the same layout with ``n_out`` features.
    """

    def __init__(
        self,
        base: nn.Module,
        params: Mapping[str, Tensor],
        *,
        run_dim: int = 0,
        evaluate: str = "vmap",
        lo: Tensor | None = None,
        hi: Tensor | None = None,
        trainable: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(base, nn.Module):
            raise TypeError(f"base must be a torch.nn.Module, got {type(base)}")
        if not isinstance(params, Mapping) or not params:
            raise ValueError("params must be a non-empty mapping name -> (R, *shape) tensor")
        own = dict(base.named_parameters())
        own.update(dict(base.named_buffers()))
        runs = None
        for name, v in params.items():
            if name not in own:
                raise ValueError(f"base has no parameter or buffer {name!r}")
            if not isinstance(v, Tensor) or tuple(v.shape[1:]) != tuple(own[name].shape):
                raise ValueError(
                    f"params[{name!r}] must have shape (R, {', '.join(map(str, own[name].shape))})"
                    f", got {tuple(v.shape) if isinstance(v, Tensor) else type(v)}"
                )
            if runs is None:
                runs = v.shape[0]
            elif v.shape[0] != runs:
                raise ValueError(f"every entry of params needs the same R={runs}, {name!r} differs")
        if not is_int(run_dim) or run_dim not in (0, 1):  # (True was taken as 1)
            raise ValueError(f"run_dim must be 0 or 1, got {run_dim!r}")
        if evaluate not in EVALUATE:
            raise ValueError(f"evaluate must be one of {EVALUATE}, got {evaluate!r}")
        if evaluate == "broadcast" and (run_dim != 0 or not hasattr(base, "forward_with")):
            raise ValueError("evaluate='broadcast' needs run_dim=0 and a base with forward_with")
        if (lo is None) != (hi is None):
            raise ValueError("give both lo and hi (per-run scaling) or neither")
        self._base = (base,)  # a tuple: not a submodule, its parameters stay out of ours
        self._names = {}  # attribute name -> parameter name of the base
        for name, v in params.items():
            attr = name.replace(".", "__")
            v = v.detach().clone()
            if trainable and own[name].requires_grad:
                self.register_parameter(attr, nn.Parameter(v))
            else:
                self.register_buffer(attr, v)
            self._names[attr] = name
        self.runs, self.run_dim, self.evaluate = int(runs), int(run_dim), evaluate
        if lo is not None:
            # numbers (a list, an array) take the dtype of the parameters: a list became
            # float32, its bounds rounded (0.1 -> 0.10000000149)
            dtype = next(iter(params.values())).dtype
            lo, hi = (
                v if isinstance(v, Tensor) else torch.as_tensor(v, dtype=dtype) for v in (lo, hi)
            )
            if lo.shape != (self.runs,) or hi.shape != (self.runs,):
                raise ValueError(
                    f"lo and hi must have shape ({self.runs},), got {tuple(lo.shape)} and "
                    f"{tuple(hi.shape)}"
                )
            bad = ~(torch.isfinite(lo) & torch.isfinite(hi) & (hi > lo))
            if bool(bad.any()):  # (hi == lo divided by zero: inf or NaN outputs)
                r = int(bad.nonzero()[0, 0])
                raise ValueError(
                    f"lo and hi must be finite with hi > lo for every run (the scale hi - lo "
                    f"divides), got lo={float(lo[r])!r}, hi={float(hi[r])!r} for run {r}"
                )
            self.register_buffer("lo", lo.detach().clone())
            self.register_buffer("scale", (hi - lo).detach().clone())
        else:
            self.lo = self.scale = None
        self.n_in = getattr(base, "n_in", getattr(base, "n_inputs", None))
        self.n_out = getattr(base, "n_out", None)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_modules(cls, modules: Sequence[nn.Module], **options) -> StackedLearner:
        """Stack the parameters of ``R`` structurally identical modules (run ``r`` = module
        ``r``); the base is a copy of the first module."""
        modules = list(modules)
        if not modules:
            raise ValueError("modules must contain at least one module")
        names = [n for n, _ in modules[0].named_parameters()]
        params = {
            n: torch.stack([dict(mod.named_parameters())[n].detach() for mod in modules])
            for n in names
        }
        return cls(copy.deepcopy(modules[0]), params, **options)

    @classmethod
    def from_theta(
        cls, base: nn.Module, theta: Tensor, params: Selector = None, **options
    ) -> StackedLearner:
        """``R`` flat parameter vectors ``theta`` ``(R, n)`` of ``base`` (the layout of
        :class:`ParameterBridge`, e.g. ``KalmanOptimizer(runs=R).theta``).

        ``params`` selects the parameters ``theta`` holds, as for :class:`ParameterBridge`
        (default: those with ``requires_grad``); pass the names of an optimiser's group that
        holds fewer (``opt.bridge.names``). The others are shared by all runs.
        """
        if not isinstance(theta, Tensor) or theta.dim() != 2:
            raise ValueError("theta must have shape (R, n)")
        bridge = ParameterBridge(base, params)
        if theta.shape[-1] != bridge.numel:
            raise ValueError(
                f"theta has {theta.shape[-1]} entries per run, but the parameters selected in "
                f"base ({', '.join(bridge.names)}) have {bridge.numel}: pass params=[names] "
                "of the parameters theta holds (a KalmanOptimizer's opt.bridge.names)"
            )
        return cls(base, bridge.unflatten(theta), **options)

    @property
    def base(self) -> nn.Module:
        return self._base[0]

    def _apply(self, fn, recurse: bool = True):
        # .to(device), .double(), ...: the base is no submodule (its parameters stay out of
        # ours), yet forward uses its buffers (an LS-SVR's support vectors), so it goes along
        # as a copy whose tensors are the converted ones (the caller's module, and any stack
        # sharing it through select(), keep theirs; nothing is copied twice)
        super()._apply(fn, recurse)
        base = self._base[0]
        memo: dict[int, Tensor] = {}
        for t in list(base.parameters()) + list(base.buffers()):
            new = fn(t.detach())
            if new.dtype != t.dtype or new.device != t.device or new.data_ptr() != t.data_ptr():
                is_param = isinstance(t, nn.Parameter)
                memo[id(t)] = nn.Parameter(new, t.requires_grad) if is_param else new
        if memo:  # something moved (a no-op .to() keeps the base as it is)
            for t in list(base.parameters()) + list(base.buffers()):
                memo.setdefault(id(t), t)  # unmoved tensors are shared, not copied
            self._base = (copy.deepcopy(base, memo),)
        return self

    def parameter_sets(self) -> dict[str, Tensor]:
        """``{name: (R, *shape)}``: the per-run values under the base's parameter names."""
        return {name: getattr(self, attr) for attr, name in self._names.items()}

    def module(self, r: int) -> nn.Module:
        """Run ``r`` as a plain copy of the base module."""
        mod = copy.deepcopy(self.base)
        own = dict(mod.named_parameters())
        own.update(dict(mod.named_buffers()))
        with torch.no_grad():
            for name, v in self.parameter_sets().items():
                own[name].copy_(v[r])
        return mod

    def select(self, index) -> StackedLearner:
        """The runs picked by ``index`` (a ``(R,)`` bool mask, an int, a sequence of ints, a
        slice); an empty index, like an all-False mask, picks no run (``runs == 0``)."""
        idx = _index(index, self.runs)
        params = {name: v[idx] for name, v in self.parameter_sets().items()}
        trainable = any(isinstance(v, nn.Parameter) for v in self.parameter_sets().values())
        scaled = {} if self.lo is None else {"lo": self.lo[idx], "hi": (self.lo + self.scale)[idx]}
        return StackedLearner(
            self.base,
            params,
            run_dim=self.run_dim,
            evaluate=self.evaluate,
            trainable=trainable,
            **scaled,
        )

    # ---------------------------------------------------------------- evaluation
    def _runs_first(self, x: Tensor) -> Tensor:
        if not isinstance(x, Tensor) or x.dim() < 2:
            raise ValueError(f"x must be a tensor with the run axis at dim {self.run_dim}")
        xr = x.movedim(self.run_dim, 0) if self.run_dim else x
        if xr.shape[0] != self.runs or (self.n_in is not None and xr.shape[-1] != self.n_in):
            where = "(R, ..., n_in)" if self.run_dim == 0 else "(B, R, ..., n_in)"
            raise ValueError(
                f"x must have shape {where} with R={self.runs} (runs at dim {self.run_dim}) and "
                f"n_in={self.n_in}, got {tuple(x.shape)}"
            )
        return xr

    def _scale_shape(self, v: Tensor, ndim: int) -> Tensor:
        return v.reshape(self.runs, *([1] * (ndim - 1)))

    def forward(self, x: Tensor) -> Tensor:
        xr = self._runs_first(x)
        if self.lo is not None:
            xr = (xr - self._scale_shape(self.lo, xr.dim())) / self._scale_shape(
                self.scale, xr.dim()
            )
        R, m = self.runs, xr.shape[-1]
        params = self.parameter_sets()
        base = self.base
        if self.evaluate == "broadcast":
            # every parameter set on every run's rows, (R, R B, o); keep run r's own block
            B = xr[0].numel() // m
            out = base.forward_with(params, xr.reshape(R * B, m))
            out = out.reshape(R, R, B, -1).diagonal(0, 0, 1).movedim(-1, 0)  # (R, B, o)
        else:
            xf = xr if xr.dim() == 3 else xr.reshape(R, -1, m)
            out = vmap(lambda p, xi: functional_call(base, p, (xi,)))(params, xf)
        out = out.reshape(*xr.shape[:-1], out.shape[-1])
        if self.lo is not None:
            out = out * self._scale_shape(self.scale, out.dim()) + self._scale_shape(
                self.lo, out.dim()
            )
        return out.movedim(0, self.run_dim) if self.run_dim else out

    def input_gradient(self, x: Tensor) -> Tensor:
        """``d out / d x``: ``(..., n_out, n_in)`` for ``x`` in the call layout, or
        ``(R B, n_out, n_in)`` for ``x`` ``(R B, n_in)``, the run-major flattening of a
        runs-leading batch (as :func:`~prognos_torch.prognosis.learner_transition_model` passes
        it)."""
        m = x.shape[-1]
        flat = x.dim() == 2 and self.run_dim == 0
        with torch.enable_grad():
            xr = x.detach()
            if flat:
                xr = xr.reshape(self.runs, -1, m)
            xr = xr.requires_grad_(True)
            out = self(xr)
            grads = [
                torch.autograd.grad(out[..., o].sum(), xr, retain_graph=o + 1 < out.shape[-1])[0]
                for o in range(out.shape[-1])
            ]
        g = torch.stack(grads, dim=-2)  # (..., n_out, n_in)
        return g.reshape(-1, out.shape[-1], m) if flat else g

    def extra_repr(self) -> str:
        return (
            f"runs={self.runs}, base={type(self.base).__name__}, run_dim={self.run_dim}, "
            f"evaluate={self.evaluate!r}, scaled={self.lo is not None}"
        )


def fit_together(
    modules: Sequence[nn.Module], make_optimizer, train: tuple[Tensor, Tensor], **fit_options
) -> StackedLearner:
    """Train ``R`` modules at once on the same data with one gradient optimiser.

    The modules are stacked with ``run_dim=1`` and ``trainable=True``, the data ``(X, Y)``
    repeated over the run axis, and :func:`~prognos_torch.optim.fit` minimises
    :func:`run_sum_mse`: for an element-wise optimiser (Adam, SGD) this is ``R`` independent
    trainings on the same mini-batches.

    Args:
        modules: ``R`` structurally identical modules (their initialisations).
        make_optimizer: ``parameters -> torch.optim.Optimizer``, e.g.
            ``lambda ps: torch.optim.Adam(ps, lr=1e-2)``.
        train: ``(X, Y)``, samples along dim 0.
        fit_options: passed to :func:`~prognos_torch.optim.fit` (epochs, batch_size, ...);
            ``val=(X_val, Y_val)``, samples along dim 0, is repeated over the runs as
            ``train`` is (its metrics, and the ``History`` that early stopping reads, are over
            all runs' outputs: one best epoch for the stack).
    Returns:
        The trained runs as a runs-leading :class:`StackedLearner`.
    """
    stack = StackedLearner.from_modules(modules, run_dim=1, trainable=True)
    R = stack.runs

    def repeated(data, name):  # (X, Y) -> (X, Y) with the run axis at dim 1
        _check_data(data, name)
        return tuple(v.unsqueeze(1).expand(-1, R, *v.shape[1:]) for v in data)

    if fit_options.get("val") is not None:
        fit_options = dict(fit_options, val=repeated(fit_options["val"], "val"))
    opt = make_optimizer(stack.parameters())
    fit(stack, opt, repeated(train, "train"), loss_fn=run_sum_mse, **fit_options)
    return StackedLearner(stack.base, stack.parameter_sets())


def _share_the_rest(modules: Sequence[nn.Module], bridge: ParameterBridge) -> bool:
    """True if the modules differ only in the tensors the bridge puts into the state."""
    ref = modules[0]
    skip = set(bridge.names)
    fixed = [(n, t) for n, t in ref.named_parameters() if n not in skip]
    fixed += list(ref.named_buffers())
    for mod in modules[1:]:
        own = dict(mod.named_parameters())
        own.update(dict(mod.named_buffers()))
        if any(n not in own or not torch.equal(own[n], t) for n, t in fixed):
            return False
    return True


def kalman_runs_optimizer(
    base: nn.Module, modules: Sequence[nn.Module], **kalman_options
) -> KalmanOptimizer:
    """One :class:`~prognos_torch.optim.KalmanOptimizer` with ``runs=R`` on ``base``, run ``r``
    starting from the parameters of ``modules[r]`` (structurally identical to ``base`` and
    sharing every tensor outside the Kalman state with it). ``kalman_options``: filter, P0, Q,
    R, ..."""
    bridge = ParameterBridge(base)
    if not _share_the_rest([base, *modules], bridge):  # (each run evaluated base's instead)
        raise ValueError(
            "the modules differ from base outside the parameters in the Kalman state (a fixed "
            "layer, a buffer): the runs of one optimiser share base's; train them separately "
            "(fit_kalman_runs(..., batched=False))"
        )
    theta0 = bridge.stack(modules)
    return KalmanOptimizer(base, runs=len(modules), theta0=theta0, **kalman_options)


def fit_kalman_runs(
    modules: Sequence[nn.Module],
    train: tuple[Tensor, Tensor],
    *,
    batched: bool | None = None,
    fit_options: Mapping | None = None,
    **kalman_options,
) -> StackedLearner:
    """Train ``R`` modules with Kalman optimisers (on the same data, or each on its own) and
    stack them.

    With ``batched`` (default: whenever the modules share every tensor outside the Kalman
    state, e.g. ANFIS initialisations; not ELMs with their own random hidden layers) one
    :class:`~prognos_torch.optim.KalmanOptimizer` with ``runs=R`` starts from the ``R``
    parameter vectors (one engine call per step); otherwise each module gets its own.

    Args:
        modules: ``R`` structurally identical modules; the non-batched path trains them in
            place.
        train: ``(X, Y)``; with ``per_run_data=True`` (a Kalman option) ``(R, N, ...)`` each,
            run ``r``'s data for module ``r`` on either path (``val`` likewise).
        fit_options: passed to :func:`~prognos_torch.optim.fit` (epochs, batch_size, ...).
            Early stopping reads the mean over runs on the batched path (one best epoch for
            all runs), each run's own value on the other.
        kalman_options: passed to :class:`~prognos_torch.optim.KalmanOptimizer` (filter, P0,
            Q, R, per_run_data, ...); ``runs`` and ``theta0`` are set here (a ``TypeError``).
    """
    modules = list(modules)
    if not modules:
        raise ValueError("modules must contain at least one module")
    fixed = sorted(k for k in ("runs", "theta0") if k in kalman_options)
    if fixed:
        raise TypeError(
            f"fit_kalman_runs sets {fixed} itself (runs = len(modules), each run starting from "
            "its module's parameters): leave them out of the options"
        )
    fit_options = dict(fit_options or {})
    base = modules[0]
    bridge = ParameterBridge(base)
    if batched is None:
        batched = _share_the_rest(modules, bridge)
    if batched:
        opt = kalman_runs_optimizer(base, modules, **kalman_options)
        fit(base, opt, train, **fit_options)
        return StackedLearner.from_theta(base, opt.theta)
    per_run = kalman_options.pop("per_run_data", False)
    R = len(modules)
    if per_run:  # run r's data (and validation data) for module r
        train = _check_data(train, "train", R)
        if fit_options.get("val") is not None:
            fit_options["val"] = _check_data(fit_options["val"], "val", R)
    for r, mod in enumerate(modules):
        opts = fit_options
        if per_run and opts.get("val") is not None:
            opts = dict(opts, val=tuple(v[r] for v in opts["val"]))
        data = tuple(v[r] for v in train) if per_run else train
        fit(mod, KalmanOptimizer(mod, **kalman_options), data, **opts)
    return StackedLearner.from_modules(modules)


class StackedForecaster:
    """``R`` runs x ``C`` channels of measurement forecasters as one forecaster.

    A :class:`~prognos_torch.prognosis.MeasurementForecaster` shares its learners (e.g. the
    random hidden layers of its ROS-ELMs) across batch dims. Packing run ``r``'s ``C`` learners
    into channels ``r C .. r C + C - 1`` of one forecaster gives each run its own learners and
    online state while the filters stay batched over runs. Implements the forecaster protocol
    of :func:`~prognos_torch.prognosis.rolling_fault_prediction` (``initialized``, ``copy``,
    ``initialize``, ``forecast``, ``update``) with the run axis after time:
    ``initialize(z0 (N0, R, C))``, ``forecast(n) -> (n, R, C)``, ``update(z (R, C))``.

    Args:
        inner: a forecaster with ``R C`` channels (``learners``, ``p``, ``lam``, ``online``).
        runs, channels: ``R`` and ``C``.
    """

    def __init__(self, inner, runs: int, channels: int) -> None:
        runs, channels = check_pos_int(runs, "runs"), check_pos_int(channels, "channels")
        if len(inner.learners) != runs * channels:
            raise ValueError(
                f"inner must have runs x channels = {runs * channels} channels, got "
                f"{len(inner.learners)}"
            )
        self.inner, self.runs, self.channels = inner, int(runs), int(channels)

    @classmethod
    def from_forecasters(cls, forecasters: Sequence) -> StackedForecaster:
        """Pack ``R`` uninitialised forecasters with ``C`` channels each (run ``r`` =
        ``forecasters[r]``); they must share ``p``, ``lam`` and ``online``."""
        fcs = list(forecasters)
        if not fcs:
            raise ValueError("forecasters must hold at least one forecaster")
        f0 = fcs[0]
        for f in fcs:
            if (f.p, f.lam, f.online, len(f.learners)) != (
                f0.p,
                f0.lam,
                f0.online,
                len(f0.learners),
            ):
                raise ValueError("every forecaster needs the same p, lam, online and channels")
            if f.initialized:
                raise ValueError("the forecasters must not be initialised yet")
        learners = [lr for f in fcs for lr in f.learners]
        inner = type(f0)(learners, f0.p, lam=f0.lam, online=f0.online)
        return cls(inner, len(fcs), len(f0.learners))

    def select(self, index: slice) -> StackedForecaster:
        """The runs in ``index`` (a slice), as a new uninitialised forecaster."""
        if not isinstance(index, slice):
            raise TypeError("index must be a slice of runs")
        f0, C = self.inner, self.channels
        runs = range(self.runs)[index]
        if not runs:  # (it failed on the inner forecaster's learners, C >= 1)
            raise ValueError(f"index {index!r} selects no run of the {self.runs} runs")
        learners = [f0.learners[r * C + c] for r in runs for c in range(C)]
        return StackedForecaster(
            type(f0)(learners, f0.p, lam=f0.lam, online=f0.online), len(runs), C
        )

    @property
    def initialized(self) -> bool:
        return self.inner.initialized

    def copy(self) -> StackedForecaster:
        return StackedForecaster(self.inner.copy(), self.runs, self.channels)

    def _check(self, z, name: str, shape: str, lead: int) -> None:
        """``z`` ends with ``(R, C)`` after ``lead`` dims (a reshape took any tensor of as many
        entries: ``(C, R)`` swapped the runs and channels, silently)."""
        want = (self.runs, self.channels)
        if not isinstance(z, Tensor) or z.dim() != lead + 2 or tuple(z.shape[lead:]) != want:
            got = tuple(z.shape) if isinstance(z, Tensor) else type(z).__name__
            raise ValueError(
                f"{name} must have shape {shape} with R={self.runs} runs and C={self.channels} "
                f"channels, got {got}"
            )

    def initialize(self, z0: Tensor) -> StackedForecaster:
        """Train on ``z0`` ``(N0, R, C)``."""
        self._check(z0, "z0", "(N0, R, C)", 1)
        self.inner.initialize(z0.reshape(z0.shape[0], self.runs * self.channels))
        return self

    def forecast(self, n: int) -> Tensor:
        """``(n, R, C)`` forecasts."""
        out = self.inner.forecast(n)
        return out.reshape(out.shape[0], self.runs, self.channels)

    def update(self, z: Tensor) -> StackedForecaster:
        """Absorb the measurement ``z`` ``(R, C)``."""
        self._check(z, "z", "(R, C)", 0)
        self.inner.update(z.reshape(self.runs * self.channels))
        return self
