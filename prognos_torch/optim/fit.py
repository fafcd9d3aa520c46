"""One training loop for Kalman-filter and gradient optimisers.

:func:`fit` trains a module with any of

* a :class:`~prognos_torch.optim.kalman.KalmanOptimizer` (``step(inputs, targets)``, one filter
  step per mini-batch, no gradients), including a batch of Monte Carlo runs (``runs=R``);
* a gradient optimiser such as ``torch.optim.Adam`` or ``torch.optim.SGD``, and
  ``torch.optim.LBFGS``: ``step(closure)`` with a closure that evaluates the loss on the
  mini-batch and calls ``loss.backward()``.

Comparisons are like for like: the same mini-batches in the same order (``shuffle`` draws one
permutation per epoch from ``generator``), the same number of passes, and the same metrics,
evaluated after every epoch on the whole training set (and ``val``) in float64.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from ..core.validation import check_finite, has_missing, is_int
from .kalman import KalmanOptimizer

__all__ = ["fit", "History", "METRICS"]


def _observed_mean(v: Tensor, target: Tensor, dims) -> Tensor:
    """Mean of ``v`` (a function of ``pred - target``) over ``dims``, where the target is
    observed: NaN targets (missing) are left out, a NaN of ``v`` where the target is observed
    (a diverged prediction) is kept."""
    obs = ~torch.isnan(target)
    if bool(obs.all()):
        return v.mean(dims)
    obs = obs.expand(v.shape)
    return torch.where(obs, v, 0.0).sum(dims) / obs.sum(dims)


def _mae(pred: Tensor, target: Tensor, dims) -> Tensor:
    return _observed_mean((pred - target).abs(), target, dims)


def _rmse(pred: Tensor, target: Tensor, dims) -> Tensor:
    return _observed_mean((pred - target).square(), target, dims).sqrt()  # paper 003 Eq. 49


def _mse(pred: Tensor, target: Tensor, dims) -> Tensor:
    return _observed_mean((pred - target).square(), target, dims)


def _observed_mse(pred: Tensor, target: Tensor) -> Tensor:
    """The default loss of gradient optimisers when some targets are missing (NaN): the mean
    squared error over the observed targets, 0 with no gradient for a mini-batch with none."""
    obs = ~torch.isnan(target)
    d = torch.where(obs, pred - target, 0.0)
    return d.square().sum() / obs.sum().clamp(min=1)


_observed_mse.handles_missing = True  # type: ignore[attr-defined]


#: Built-in metrics (paper 003 Eq. 48-49), computed in float64 over the output entries whose
#: target is observed (NaN targets are missing and left out). Non-finite predictions give NaN
#: (a diverged run is reported, not raised).
METRICS: dict[str, Callable[[Tensor, Tensor, tuple[int, ...]], Tensor]] = {
    "mae": _mae,
    "rmse": _rmse,
    "mse": _mse,
}


@dataclass
class History:
    """Per-epoch record of a :func:`fit` call.

    Each metric value is a float64 tensor: ``()`` for one run, ``(R,)`` for ``R`` Monte Carlo
    runs of a :class:`KalmanOptimizer`.

    Attributes:
        metrics: metric names, in order.
        epoch: 1-based epoch numbers.
        train: ``{metric: [value per epoch]}`` on the whole training set after each epoch.
        val: the same on ``val`` (empty lists if no ``val`` was given).
        loss: mean training loss of the optimiser steps in each epoch (Kalman: the mean squared
            innovation before each update; gradient optimisers: ``loss_fn`` before each step).
        time: seconds spent in the optimiser steps of each epoch (evaluation excluded; with
            ``compile=True`` the compile time excluded too; on CUDA the device is synchronised
            at the start and end of the epoch, so the time includes the queued kernels).
        compile_time: seconds spent compiling in each epoch (``compile=True``; else 0).
        steps: number of optimiser steps taken in total.
        best_epoch: epoch with the lowest mean validation value of the first metric (``None``
            without ``val``).
        stopped_early: whether early stopping ended the training.

    With early stopping and ``restore_best``, the module and the optimiser end at
    ``best_epoch``, while the lists (and :meth:`last`) still run to the last epoch trained:
    the restored model's values are ``train[m][best_epoch - 1]`` and ``val[m][best_epoch - 1]``.
    """

    metrics: tuple[str, ...]
    epoch: list[int] = field(default_factory=list)
    train: dict[str, list[Tensor]] = field(default_factory=dict)
    val: dict[str, list[Tensor]] = field(default_factory=dict)
    loss: list[Tensor] = field(default_factory=list)
    time: list[float] = field(default_factory=list)
    compile_time: list[float] = field(default_factory=list)
    steps: int = 0
    best_epoch: int | None = None
    stopped_early: bool = False

    @property
    def train_time(self) -> float:
        """Total seconds spent in optimiser steps."""
        return float(sum(self.time))

    def last(self, split: str = "train") -> dict[str, Tensor]:
        """Metric values of the last epoch on ``"train"`` or ``"val"``."""
        src = {"train": self.train, "val": self.val}.get(split)
        if src is None:
            raise ValueError(f"split must be 'train' or 'val', got {split!r}")
        return {k: v[-1] for k, v in src.items() if v}


def _check_data(data, name: str, runs: int | None = None) -> tuple[Tensor, Tensor]:
    """``(X, Y)`` with rows along dim 0, or along dim 1 after ``runs`` (per-run data)."""
    if not (isinstance(data, (tuple, list)) and len(data) == 2):
        raise TypeError(f"{name} must be a pair (X, Y) of tensors")
    X, Y = data
    if not isinstance(X, Tensor) or not isinstance(Y, Tensor):
        raise TypeError(f"{name} must be a pair (X, Y) of tensors, got {type(X)}, {type(Y)}")
    for what, v in (("inputs X", X), ("targets Y", Y)):
        if not v.is_floating_point():  # (an int or bool Y was taken by the MSE as 0/1 values)
            raise TypeError(f"{name} {what} must be a floating-point tensor, got {v.dtype}")
    if runs is not None:
        if X.dim() < 2 or Y.dim() < 2 or X.shape[0] != runs or Y.shape[0] != runs:
            raise ValueError(
                f"{name}: with per-run data X and Y must have shape (runs={runs}, N, ...), got "
                f"{tuple(X.shape)} and {tuple(Y.shape)}"
            )
        if X.shape[1] != Y.shape[1] or X.shape[1] == 0:
            raise ValueError(
                f"{name}: X and Y must have the same non-zero number of rows (runs, N, ...), "
                f"got {tuple(X.shape)} and {tuple(Y.shape)}"
            )
        return X, Y
    if X.dim() < 1 or Y.dim() < 1 or X.shape[0] != Y.shape[0] or X.shape[0] == 0:
        raise ValueError(
            f"{name}: X and Y must have the same non-zero number of rows (N, ...), got "
            f"{tuple(X.shape)} and {tuple(Y.shape)}"
        )
    return X, Y


def _check_values(X: Tensor, Y: Tensor, name: str, runs: int | None, observed: bool = True) -> bool:
    """Finite inputs; targets finite or NaN (missing), with at least one observed target (per
    run with per-run data) when ``observed``. Returns whether any target is missing."""
    check_finite(X, f"{name} inputs X")
    if not has_missing(Y, f"{name} targets Y", "target"):
        return False
    if not observed:
        return True
    seen = (~torch.isnan(Y)).reshape(runs or 1, -1).any(-1)
    if not bool(seen.all()):
        whose = "" if runs is None else f" of run {int((~seen).nonzero()[0, 0])}"
        raise ValueError(f"{name} targets Y{whose} are all missing (NaN): nothing to fit or score")
    return True


def _metric_fns(metrics) -> list[tuple[str, Callable]]:
    if isinstance(metrics, str):
        metrics = (metrics,)
    out = []
    for m in metrics:
        if isinstance(m, str):
            if m not in METRICS:
                raise ValueError(f"metrics: unknown metric {m!r}; choose from {sorted(METRICS)}")
            out.append((m, METRICS[m]))
        elif callable(m):
            name = getattr(m, "__name__", "metric")
            out.append((name, lambda p, t, dims, m=m: m(p, t)))
        else:
            raise TypeError(f"metrics must contain names or callables, got {type(m)}")
    if not out:
        raise ValueError("metrics must name at least one metric")
    names = [name for name, _ in out]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise ValueError(
            f"metrics: the names {twice} are given more than once (a callable is named by its "
            "__name__, 'metric' without one); History keeps one list per name, so give each "
            "callable its own name (a def, or set fn.__name__)"
        )
    return out


def _predict(module, optimizer, X: Tensor, Y: Tensor, name: str, shown=None) -> Tensor:
    """The predictions that the metrics score: ``optimizer.predict`` for ``R`` runs
    (``(R, N, ...)``; per-run data ``(R, N, ...)`` in, the same out), else ``module(X)``; of
    exactly the targets' shape (after the runs): nothing broadcast. ``shown``: the shape of
    the whole targets, named in the error when ``Y`` is their first sample."""
    runs = optimizer.runs if isinstance(optimizer, KalmanOptimizer) else None
    pred = module(X) if runs is None else optimizer.predict(X)
    lead = (runs,) if runs is not None and not optimizer.per_run_data else ()
    if not isinstance(pred, Tensor) or tuple(pred.shape) != lead + tuple(Y.shape):
        if not isinstance(pred, Tensor):
            raise TypeError(f"the module must return one tensor, got {type(pred).__name__}")
        rows = len(lead) + (1 if runs is not None and optimizer.per_run_data else 0) + 1
        Ys = tuple(Y.shape if shown is None else shown)
        want = Ys[: rows - len(lead)] + tuple(pred.shape[rows:])  # the rows, then the output
        raise ValueError(
            f"{name} targets Y must have shape {want} as the model output (for inputs of "
            f"shape {tuple(X.shape)}: {tuple(pred.shape)}), got {Ys}: a metric would broadcast "
            "them"
        )
    return pred


def _check_outputs(module, optimizer, X: Tensor, Y: Tensor, name: str, per_run: bool) -> None:
    """The prediction of the first sample has the targets' shape: checked before any step, so
    that a bad ``val`` is refused before an epoch has trained the module (it failed after)."""
    first = slice(0, 1)
    x1, y1 = (X[:, first], Y[:, first]) if per_run else (X[first], Y[first])
    modes = _modes(module)
    module.eval()  # (no running statistics moved by this look at the output's shape)
    try:
        with torch.no_grad():
            _predict(module, optimizer, x1, y1, name, Y.shape)
    finally:
        _restore_modes(modes)


def _modes(module: nn.Module) -> list[tuple[nn.Module, bool]]:
    """The training flag of every submodule (a layer put in eval() by the user keeps it)."""
    return [(m, m.training) for m in module.modules()]


def _restore_modes(modes: list[tuple[nn.Module, bool]]) -> None:
    for m, training in modes:
        m.training = training


def _train_mode(module: nn.Module, modes: list[tuple[nn.Module, bool]]) -> None:
    """``module.train()``, except for the submodules the caller had put in ``eval()`` inside a
    module in training mode (a frozen BatchNorm, a Dropout switched off for a Kalman
    optimiser, as its error message advises): they stay in eval mode."""
    module.train()
    if modes[0][1]:
        for m, training in modes:
            if not training:
                m.training = False


@torch.no_grad()
def _evaluate(module, optimizer, X: Tensor, Y: Tensor, fns, name: str) -> dict[str, Tensor]:
    pred = _predict(module, optimizer, X, Y, name)
    runs = isinstance(optimizer, KalmanOptimizer) and optimizer.runs is not None
    dims = tuple(range(1 if runs else 0, pred.dim()))
    p64, t64 = pred.to(torch.float64), Y.to(device=pred.device, dtype=torch.float64)
    return {name: fn(p64, t64, dims) for name, fn in fns}


def fit(
    module: nn.Module,
    optimizer: torch.optim.Optimizer,
    train: tuple[Tensor, Tensor],
    *,
    epochs: int = 1,
    batch_size: int = 1,
    shuffle: bool = False,
    generator: torch.Generator | None = None,
    val: tuple[Tensor, Tensor] | None = None,
    early_stopping: int | None = None,
    restore_best: bool = True,
    drop_last: bool = False,
    progress: bool | None = True,
    metrics: Sequence[str | Callable] = ("mae", "rmse"),
    loss_fn: Callable[[Tensor, Tensor], Tensor] | None = None,
    compile: bool = False,
) -> History:
    """Train ``module`` with ``optimizer`` on ``train = (X, Y)``; the one loop for all optimisers.

    Args:
        module: the learner (the optimiser must have been built on its parameters).
        optimizer: a :class:`KalmanOptimizer` or a ``torch.optim.Optimizer`` (Adam, SGD, LBFGS,
            ...). Gradient optimisers get a closure that zeroes the gradients, evaluates
            ``loss_fn(module(xb), yb)`` and calls ``backward()``.
        train: inputs ``X`` ``(N, ...)`` and targets ``Y`` ``(N, ...)`` (``module(X).shape``);
            for a :class:`KalmanOptimizer` with ``per_run_data``, ``(R, N, ...)`` each.
            ``X`` finite; NaN in ``Y`` marks a missing target: a Kalman optimiser updates with
            the observed entries of each mini-batch (one with none observed is the filter's
            prediction alone, ``P + Q`` for the random walk; strong tracking and noise
            estimators skip a mini-batch with any target missing; a robust filter refuses
            one with some missing), the default loss of gradient optimisers and the built-in
            metrics leave them out (a metric callable gets them as they are), a gradient
            optimiser takes no step on a mini-batch with none observed, and the epoch's loss
            is the mean over the steps that observed one. Every run needs an observed target.
        epochs: number of passes over ``train``.
        batch_size: samples per optimiser step (Kalman: the measurement vector of one step).
        shuffle: draw a new order of the samples each epoch (``torch.randperm`` with
            ``generator``); otherwise the samples are used in order (time order for series).
        generator: ``torch.Generator`` for ``shuffle`` (required when ``shuffle`` is true).
        val: optional validation pair, evaluated after every epoch.
        early_stopping: patience in epochs (``None``: off): stop when the first metric on
            ``val`` (mean over runs) has not improved for that many epochs. Needs ``val``.
        restore_best: with early stopping, restore the module and optimiser state of the best
            epoch at the end (also when no stop came before ``epochs``; without early stopping
            nothing is restored, ``History.best_epoch`` is only reported).
        drop_last: skip the last mini-batch of an epoch if it is smaller than ``batch_size``
            (a Kalman optimiser with a noise estimator or strong tracking needs equal sizes).
        progress: show a ``tqdm`` progress bar (``None``: only where stderr is a terminal).
        metrics: names in :data:`METRICS` or callables ``(pred, target) -> Tensor``.
        loss_fn: loss of gradient optimisers (default: mean squared error). With missing
            targets a loss_fn must leave them out itself and say so by an attribute
            ``loss_fn.handles_missing = True`` (as :func:`~prognos_torch.optim.run_sum_mse`).
        compile: a :class:`KalmanOptimizer` runs each epoch's full mini-batches as one
            compiled sequence (:meth:`KalmanOptimizer.steps` with ``compile=True``: the same
            numbers as eager steps up to rounding, float64 ``<= 1e-12``); a last, smaller
            mini-batch is stepped eagerly. The compile time is kept apart
            (:attr:`History.compile_time`), not in :attr:`History.time`. Pays on long passes
            of small steps (paper 003's ANFIS: about 10x on one SRUKF or EKF run after a
            compile of 20-40 s); eager is the default.
    Returns:
        :class:`History`.
    """
    return _fit(
        module,
        optimizer,
        train,
        epochs=epochs,
        batch_size=batch_size,
        shuffle=shuffle,
        generator=generator,
        val=val,
        early_stopping=early_stopping,
        restore_best=restore_best,
        drop_last=drop_last,
        progress=progress,
        metrics=metrics,
        loss_fn=loss_fn,
        compile=compile,
    )


def _checked(
    module: nn.Module, optimizer: torch.optim.Optimizer, train, val, epochs, batch_size,
    shuffle: bool, generator, early_stopping, metrics, loss_fn, compile, observed: bool,
) -> tuple:  # fmt: skip
    """The checks of :func:`fit` before any step, as ``(X, Y, Xv, Yv, missing, per_run, kalman,
    fns, loss_fn)`` (``Xv``, ``Yv`` ``None`` without ``val``; ``missing``: ``train`` has NaN
    targets; ``fns``: the named metrics; ``loss_fn`` the default one where ``None``)."""
    Xv = Yv = None
    per_run = isinstance(optimizer, KalmanOptimizer) and optimizer.per_run_data
    runs = optimizer.runs if per_run else None
    X, Y = _check_data(train, "train", runs)
    missing = _check_values(X, Y, "train", runs, observed)
    if val is not None:
        Xv, Yv = _check_data(val, "val", runs)
        _check_values(Xv, Yv, "val", runs)
    if not isinstance(optimizer, torch.optim.Optimizer):
        raise TypeError(f"optimizer must be a torch.optim.Optimizer, got {type(optimizer)}")
    if not isinstance(module, nn.Module):
        raise TypeError(f"module must be a torch.nn.Module, got {type(module)}")
    for name, v in (("epochs", epochs), ("batch_size", batch_size)):
        if not is_int(v) or v < 1:
            raise ValueError(f"{name} must be a positive int, got {v!r}")
    if shuffle and not isinstance(generator, torch.Generator):
        raise ValueError("shuffle=True needs an explicit torch.Generator (generator=...)")
    if early_stopping is not None:
        if not is_int(early_stopping):
            raise ValueError(
                f"early_stopping must be None or a positive int, got {early_stopping!r}"
            )
        if early_stopping < 1:
            raise ValueError(f"early_stopping must be a positive int, got {early_stopping}")
        if val is None:
            raise ValueError("early_stopping needs val=(X_val, Y_val)")
    fns = _metric_fns(metrics)
    kalman = isinstance(optimizer, KalmanOptimizer)
    if kalman and optimizer.module is not module:
        raise ValueError("optimizer is a KalmanOptimizer built on a different module")
    if loss_fn is None:
        loss_fn = _observed_mse if missing else nn.functional.mse_loss
    elif missing and not kalman and not getattr(loss_fn, "handles_missing", False):
        raise ValueError(
            "train targets contain NaN (missing): the default loss leaves them out, a custom "
            "loss_fn would get them; drop those samples, or leave them out in loss_fn and "
            "mark it with loss_fn.handles_missing = True"
        )
    if not isinstance(compile, bool):
        raise TypeError(f"compile must be a bool, got {type(compile).__name__}")
    if compile and not kalman:
        raise ValueError("compile=True needs a KalmanOptimizer (gradient optimisers run eager)")
    if compile and optimizer.per_run_data:
        raise ValueError("compile=True needs per_run_data=False")
    if compile and missing:
        raise ValueError(
            "train targets contain NaN (missing): the compiled pass needs complete targets; "
            "compile=False steps update with the observed ones"
        )

    if kalman and val is not None:  # as the steps check train's, before any step
        b = optimizer.bridge
        for what, v in (("val inputs X", Xv), ("val targets Y", Yv)):
            if v.dtype != b.dtype:
                raise TypeError(
                    f"{what} has dtype {v.dtype} but the module parameters have dtype {b.dtype}"
                )
            if v.device != b.device:
                raise ValueError(f"{what} is on {v.device} but the module is on {b.device}")
    if not kalman and X.shape[0] > 0:  # (the Kalman steps check theirs before updating)
        modes = _modes(module)
        module.eval()  # (no running statistics moved by this look at the output's shape)
        try:
            with torch.no_grad():
                out = module(X[:1])
        finally:
            _restore_modes(modes)
        if tuple(out.shape[1:]) != tuple(Y.shape[1:]):
            raise ValueError(
                f"train targets must have shape (N, ...) = (N, {', '.join(map(str, out.shape[1:]))})"
                f" as the model output per sample, got {tuple(Y.shape)}: a loss would broadcast "
                "them (an (N,) target against an (N, 1) output compares every pair)"
            )
    if val is not None:
        _check_outputs(module, optimizer, Xv, Yv, "val", per_run)
    return X, Y, Xv, Yv, missing, per_run, kalman, fns, loss_fn


def _epoch_steps(
    module: nn.Module, optimizer: torch.optim.Optimizer, X: Tensor, Y: Tensor, order: Tensor,
    n_batches: int, batch_size: int, shuffle: bool, per_run: bool, kalman: bool, missing: bool,
    compile: bool, loss_fn: Callable, losses: list, hist: History, bar,
) -> float:  # fmt: skip
    """One epoch's steps over the mini-batches of ``order``: the full ones through the compiled
    pass with ``compile``, the rest eager (a Kalman step, or a gradient step by a closure).
    Appends each step's loss to ``losses``, counts ``hist.steps``; returns the compile time."""
    N = X.shape[1 if per_run else 0]
    compiled_time = 0.0
    done = 0
    full = N // batch_size
    if compile and full > 0:  # (no full mini-batch: the one smaller one is eager)
        idx = order[: full * batch_size]
        xs, ys = (X[:, idx], Y[:, idx]) if per_run else (X[idx], Y[idx])
        shape = (full, batch_size)
        xs = xs.reshape(*shape, *xs.shape[1:])
        ys = ys.reshape(*shape, *ys.shape[1:])
        losses.extend(optimizer.steps(xs, ys, compile=True).to(torch.float64).unbind(0))
        compiled_time = optimizer.compile_time
        done = full
        hist.steps += full
        if bar is not None:
            bar.update(full)
    for b in range(done, n_batches):
        if shuffle:
            idx = order[b * batch_size : (b + 1) * batch_size]
            xb, yb = (X[:, idx], Y[:, idx]) if per_run else (X[idx], Y[idx])
        else:  # in order: views, no gather
            sl = slice(b * batch_size, (b + 1) * batch_size)
            xb, yb = (X[:, sl], Y[:, sl]) if per_run else (X[sl], Y[sl])
        if kalman:
            loss = optimizer.step(xb, yb).loss
        elif missing and not bool((~torch.isnan(yb)).any()):
            # no observed target: nothing to learn from, no step (a zero gradient
            # would still move a momentum optimiser); its loss is NaN, left out
            loss = torch.tensor(math.nan, dtype=torch.float64, device=X.device)
        else:

            def closure(xb=xb, yb=yb):
                optimizer.zero_grad()
                out = loss_fn(module(xb), yb)
                out.backward()
                return out

            loss = optimizer.step(closure)
            if loss is None:  # an optimiser whose step does not return the loss
                loss = torch.tensor(math.nan, dtype=torch.float64, device=X.device)
        losses.append(loss.detach().to(torch.float64))
        hist.steps += 1
        if bar is not None:
            bar.update(1)
    return compiled_time


def _fit(
    module: nn.Module,
    optimizer: torch.optim.Optimizer,
    train: tuple[Tensor, Tensor],
    *,
    epochs: int,
    batch_size: int,
    shuffle: bool,
    generator: torch.Generator | None,
    val: tuple[Tensor, Tensor] | None,
    early_stopping: int | None,
    restore_best: bool,
    drop_last: bool,
    progress: bool | None,
    metrics: Sequence[str | Callable],
    loss_fn: Callable[[Tensor, Tensor], Tensor] | None,
    compile: bool,
    observed: bool = True,
) -> History:
    """:func:`fit`; with ``observed=False`` a ``train`` whose targets (of a run) are all missing
    is taken too (a block of a stream, :mod:`~prognos_torch.optim.online`: the Kalman steps are
    predictions, a gradient optimiser takes none, the losses and metrics are NaN)."""
    X, Y, Xv, Yv, missing, per_run, kalman, fns, loss_fn = _checked(
        module,
        optimizer,
        train,
        val,
        epochs,
        batch_size,
        shuffle,
        generator,
        early_stopping,
        metrics,
        loss_fn,
        compile,
        observed,
    )
    N = X.shape[1 if per_run else 0]  # per-run data: (runs, N, ...)
    n_batches = N // batch_size if drop_last else -(-N // batch_size)
    if n_batches == 0:
        raise ValueError(f"batch_size={batch_size} with drop_last leaves no batch of N={N} samples")
    hist = History(metrics=tuple(name for name, _ in fns))
    for name, _ in fns:
        hist.train[name] = []
        hist.val[name] = []

    try:
        from tqdm.auto import tqdm

        off = None if progress is None else not progress
        bar = tqdm(total=epochs * n_batches, disable=off, desc="fit", leave=False)
    except ImportError:  # pragma: no cover - tqdm is a dependency
        bar = None

    modes = _modes(module)
    best_value, best_state, since_best = float("inf"), None, 0
    if kalman:
        # values checked once here; the steps check types, shapes, dtypes and devices (with
        # missing targets each step finds its own: the filter updates with the observed ones)
        optimizer._finite_checked = not missing
    try:
        for epoch in range(1, epochs + 1):
            if shuffle:
                # drawn where the generator lives (a CPU or a CUDA stream), used on X's device
                order = torch.randperm(N, generator=generator, device=generator.device)
                order = order.to(X.device)
            else:
                order = torch.arange(N, device=X.device)
            _train_mode(module, modes)
            losses = []
            _synchronize(X.device)  # device work queued before the epoch is not its time
            t0 = time.perf_counter()
            compiled_time = _epoch_steps(
                module,
                optimizer,
                X,
                Y,
                order,
                n_batches,
                batch_size,
                shuffle,
                per_run,
                kalman,
                missing,
                compile,
                loss_fn,
                losses,
                hist,
                bar,
            )
            _synchronize(X.device)  # the steps' queued device work is their time
            hist.time.append(time.perf_counter() - t0 - compiled_time)
            hist.compile_time.append(compiled_time)
            stacked = torch.stack(losses)
            # (a step whose targets are all missing has a NaN loss: it observed nothing)
            hist.loss.append(stacked.nanmean(0) if missing else stacked.mean(0))
            hist.epoch.append(epoch)

            module.eval()
            for name, v in _evaluate(module, optimizer, X, Y, fns, "train").items():
                hist.train[name].append(v)
            if val is not None:
                vals = _evaluate(module, optimizer, Xv, Yv, fns, "val")
                for name, v in vals.items():
                    hist.val[name].append(v)
                monitored = float(vals[hist.metrics[0]].mean())
                if monitored < best_value:
                    best_value, since_best = monitored, 0
                    hist.best_epoch = epoch
                    if early_stopping is not None and restore_best:
                        best_state = (
                            copy.deepcopy(module.state_dict()),
                            copy.deepcopy(optimizer.state_dict()),
                        )
                else:
                    since_best += 1
            if bar is not None:
                bar.set_postfix(
                    {k: f"{float(v[-1].mean()):.4g}" for k, v in hist.train.items()}, refresh=False
                )
            if early_stopping is not None and since_best >= early_stopping:
                hist.stopped_early = epoch < epochs
                break
    finally:
        if kalman:
            optimizer._finite_checked = False
        if bar is not None:
            bar.close()
        _restore_modes(modes)
    if best_state is not None and hist.best_epoch != hist.epoch[-1]:
        module.load_state_dict(best_state[0])
        optimizer.load_state_dict(best_state[1])
    return hist


def _synchronize(device: torch.device) -> None:
    """Wait for the kernels queued on ``device`` (CUDA); nothing on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
