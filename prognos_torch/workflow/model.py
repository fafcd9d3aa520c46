"""Fit a one-step learner to a series: learners and optimisers by name, embedding dimension by
validation, scaling and held-out metrics; the result is the plain record
:class:`~prognos_torch.workflow.fitted.FittedModel` (learner, scaler, config).

Pipeline of :func:`fit_series` (all float64):

1. chronological split: the last ``holdout`` values are kept for evaluation, the rest trains;
2. min-max scaling to ``[0, 1]`` fitted on the training part (:class:`MinMaxScaler`; every
   output is transformed back);
3. embedding (paper 002 Eq. 9-10): windows ``[x_{i}, ..., x_{i+m-1}]`` predict ``x_{i+m}``;
4. ``m`` when not given: paper 003 (Sec. V-A) picks ``m`` in ``{2, ..., 10}`` with the lowest
   *training* error. Training error favours large ``m``, so here the last 20 % of the training
   part is a validation set and the ``m`` with the lowest one-step validation RMSE wins. Each
   candidate is fitted with the learner's closed-form solve (ridge ELM, KKT LS-SVR, ANFIS
   least-squares consequents on data-spread premises), which is fast and ranks ``m`` the same
   way the full training would, up to noise; the chosen ``m`` is then trained with the chosen
   optimiser. ANFIS has ``2^m`` grid rules, so its candidates stop at 5;
5. training: the *natural* fit of the learner (``optimizer="closed-form"``: ridge for ELM,
   paper 000 Eq. 52-54; the KKT solve for LS-SVR, paper 002 Eq. 4; for ANFIS the premises
   spread over the data and least-squares consequents, the first half of Jang's hybrid rule) or
   an iterative optimiser through :func:`prognos_torch.optim.fit`: ``"ekf"``, ``"srukf"``,
   ``"imsrukf"`` (:class:`~prognos_torch.optim.KalmanOptimizer`, paper 003 Eq. 44-46),
   ``"adam"``, ``"lbfgs"``. Long series: above 2,000 training values (or the learner option
   ``max_support``) the LS-SVR is the fixed-size LS-SVR on ``M`` support points
   (:class:`~prognos_torch.learners.FixedSizeLSSVR`, :mod:`prognos_torch.workflow.memory`),
   and every fit first checks its memory estimate against the budget;
6. the one-step residual RMSE on the training pairs (scaled units) sets the noise of the
   forecasting model (:mod:`prognos_torch.workflow.predict`);
7. held-out metrics: the forecast from the end of the training part over the held-out tail
   (RMSE, MAE, coverage of the central band), the one-step RMSE on the tail, and the RMSE of the
   persistence forecast (last value) as a baseline.

Defaults (``optimizer=None``): ELM and LS-SVR use their closed form; ANFIS uses the EKF with
paper 003's Lorenz settings (``P0 = {alpha: 1, b: 1e-2, beta: 1e-4}``, ``Q = 1e-6``,
``R = 1e-3``, one pass), the most accurate of the Kalman optimisers in the library's
measurements (``tests/test_optim.py``).

ImSRUKF here estimates ``R`` only (Sage-Husa Eq. 43, diagonal). The library's optimiser default
also estimates ``Q`` (Eq. 41); with it, one pass of ANFIS (m = 3) training ended at a one-step
training RMSE of 0.387 on a 400-value synthetic degradation series and 0.295 on the IMS
health indicator (channel 5, [0, 1] scale), against 0.025 and 0.099 for the EKF, 0.026 and
0.102 for the SRUKF, and 0.027 and 0.083 when ImSRUKF estimates ``R`` alone. Pass
``optimizer_options={"estimate": ["Q", "R"]}`` for the library default.
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Mapping

import torch
from torch import Tensor, nn

from ..adapt.noise import SageHusa
from ..core.validation import (
    all_finite,
    check_flag,
    check_pos_int,
    check_seed,
    is_int,
    is_real,
    plain_number,
)
from ..datasets.windows import MinMaxScaler, embed
from ..learners import ANFIS, ELM, LSSVR
from ..learners.lssvr_fixed import FixedSizeLSSVR
from ..metrics import rmse
from ..optim import KalmanOptimizer
from ..optim import fit as optim_fit
from .data import Series
from .fitted import FittedModel
from .memory import MemoryBudgetError, allocation_failure, check_fit_memory, lssvr_support
from .predict import holdout_metrics

__all__ = [
    "LEARNERS",
    "OPTIMIZERS",
    "DEFAULT_OPTIMIZER",
    "FittedModel",
    "fit_series",
    "select_embedding",
    "build_learner",
    "check_names",
]

LEARNERS = ("elm", "lssvr", "anfis")
OPTIMIZERS = ("closed-form", "ekf", "srukf", "imsrukf", "adam", "lbfgs")
KALMAN = ("ekf", "srukf", "imsrukf")
DEFAULT_OPTIMIZER = {"elm": "closed-form", "lssvr": "closed-form", "anfis": "ekf"}
_ALIASES = {"closed_form": "closed-form", "closedform": "closed-form", "ridge": "closed-form",
            "kkt": "closed-form", "lstsq": "closed-form"}  # fmt: skip

#: Learner options and their defaults (scaled data in [0, 1]).
LEARNER_DEFAULTS: dict[str, dict] = {
    "elm": {"n_hidden": 20, "activation": "sigmoid", "lam": 1e-6},
    "lssvr": {"kernel": "rbf", "sigma": 0.5, "C": 100.0, "max_support": None},
    "anfis": {"n_mfs": 2, "mf": "sigmoid", "lam": 1e-8},
}
#: Optimiser options and their defaults. ``P0`` of ANFIS is per parameter (paper 003).
OPTIMIZER_DEFAULTS: dict[str, dict] = {
    "closed-form": {},
    "ekf": {"epochs": 1, "P0": None, "Q": None, "R": 1e-3},
    "srukf": {"epochs": 1, "P0": None, "Q": None, "R": 1e-3},
    "imsrukf": {"epochs": 1, "P0": None, "Q": None, "R": 1e-3, "estimate": ["R"]},
    "adam": {"epochs": 500, "lr": 1e-2},
    "lbfgs": {"epochs": 25, "lr": 1.0, "max_iter": 20},
}
#: Candidate embedding dimensions (paper 003: {2, ..., 10}; ANFIS: 2^m rules, up to 5).
M_CANDIDATES = {"elm": tuple(range(2, 11)), "lssvr": tuple(range(2, 11)), "anfis": (2, 3, 4, 5)}
#: Largest Kalman-optimiser state (the filter costs O(n^3) per step).
MAX_KALMAN_STATE = 600
VALIDATION_FRACTION = 0.2


def check_names(learner: str, optimizer: str | None) -> tuple[str, str]:
    """Normalise and validate a learner and an optimiser name (``None``: the default)."""
    if not isinstance(learner, str) or learner.lower() not in LEARNERS:
        raise ValueError(f"unknown learner {learner!r}; choose one of {', '.join(LEARNERS)}")
    learner = learner.lower()
    if optimizer is None:
        return learner, DEFAULT_OPTIMIZER[learner]
    if not isinstance(optimizer, str):
        raise ValueError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    key = _ALIASES.get(optimizer.lower(), optimizer.lower())
    if key not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    return learner, key


def _merge(defaults: dict, given: dict | None, what: str) -> dict:
    given = dict(given or {})
    unknown = set(given) - set(defaults)
    if unknown:
        raise ValueError(f"unknown {what} option(s) {sorted(unknown)}; known: {sorted(defaults)}")
    kinds = {int: ("an int", numbers.Integral), float: ("a number", numbers.Real), str: ("a name", str)}
    for key, v in given.items():  # the kind of value its default has (None, lists: free)
        kind = kinds.get(type(defaults[key]))
        if kind is not None and (isinstance(v, bool) or not isinstance(v, kind[1])):
            raise ValueError(
                f"{what} option {key} must be {kind[0]} (like {defaults[key]!r}), got {v!r}"
            )
        if kind is not None and kind[1] is not str:
            given[key] = plain_number(v)  # a NumPy scalar: the config is JSON
    out = dict(defaults)
    out.update(given)
    return out


def build_learner(
    name: str,
    m: int,
    options: dict,
    *,
    seed: int,
    dtype=torch.float64,
    device=None,
    n_rows: int | None = None,
) -> nn.Module:
    """An untrained learner with input dimension ``m`` (ELM features, ANFIS consequents and the
    fixed-size LS-SVR's support selection from a CPU generator seeded with ``seed``).

    ``n_rows`` (training values) chooses between the exact and the fixed-size LS-SVR
    (:func:`~prognos_torch.workflow.memory.lssvr_support`; a model file passes its
    ``series.n_train``); ``None`` builds the exact :class:`~prognos_torch.learners.LSSVR`.
    """
    # (manual_seed said "an integer is required" for np.int64, "expected a long" for 1.5)
    gen = torch.Generator().manual_seed(check_seed(seed))
    if name == "elm":
        net = ELM(m, int(options["n_hidden"]), 1, options["activation"], gen, dtype)
    elif name == "lssvr":
        kernel, sigma, C = options["kernel"], float(options["sigma"]), float(options["C"])
        M = None if n_rows is None else lssvr_support(n_rows, options.get("max_support"))
        if M is None:
            net = LSSVR(kernel, sigma, C, dtype=dtype)
        else:
            net = FixedSizeLSSVR(kernel, sigma, C, n_support=M, generator=gen, dtype=dtype)
    elif name == "anfis":
        net = ANFIS(m, int(options["n_mfs"]), options["mf"], 1, gen, dtype)
    else:  # pragma: no cover - names are checked before
        raise ValueError(f"unknown learner {name!r}")
    return net.to(device) if device is not None else net


def _closed_form(name: str, net: nn.Module, X: Tensor, Y: Tensor, options: dict) -> None:
    if name == "elm":
        net.fit_ridge(X, Y, float(options["lam"]))
    elif name == "lssvr":
        net.fit(X, Y)
    else:
        net.init_premises(X)
        net.init_consequents_lstsq(X, Y, float(options["lam"]))


def _predict(net: nn.Module, X: Tensor) -> Tensor:
    with torch.no_grad():
        return net(X)[..., 0]


def _pairs(z: Tensor, m: int, start: int, stop: int) -> tuple[Tensor, Tensor]:
    """Windows predicting ``z[start:stop]`` (each from the ``m`` values before it)."""
    X, Y = embed(z[start - m : stop], m)
    return X, Y


def select_embedding(
    z: Tensor,
    learner: str,
    learner_options: dict,
    candidates,
    *,
    seed: int = 0,
    progress: bool | None = False,
) -> tuple[int, dict[int, float]]:
    """Pick ``m`` by one-step validation RMSE (see the module notes; paper 003 Sec. V-A).

    Args:
        z: ``(T,)`` scaled training series.
        learner: learner name; each candidate is fitted in closed form.
        learner_options: options of :func:`build_learner`.
        candidates: embedding dimensions to try.
        progress: a ``tqdm`` bar over the candidates (``None``: only on a terminal).

    Returns:
        ``(m, {m: validation RMSE})``; every candidate validates on the same targets, the last
        ``ceil(0.2 T)`` values.
    """
    seed = check_seed(seed)
    if progress is not None:
        progress = check_flag(progress, "progress")
    if not isinstance(z, Tensor) or not z.is_floating_point() or z.dim() != 1:
        got = tuple(z.shape) if isinstance(z, Tensor) else type(z).__name__
        raise ValueError(f"z must be a floating tensor of shape (T,), got {got}")
    z = z.to(torch.float64)  # (the learners are float64; a float32 z failed in their forward)
    try:
        given = list(candidates)
    except TypeError:
        given = []
    if not given or any(not is_int(m) or m < 1 for m in given):  # (2.0: "slice indices must")
        raise ValueError(f"candidates must be positive ints, got {candidates!r}")
    candidates = [int(m) for m in given]
    T = z.shape[0]
    n_val = max(1, math.ceil(VALIDATION_FRACTION * T))
    split = T - n_val
    usable = [m for m in candidates if split - m >= m + 2]
    if not usable:
        raise ValueError(
            f"the training part has {T} values: too short to choose the embedding dimension "
            f"among {list(candidates)} (give m explicitly or use more data)"
        )
    scores: dict[int, float] = {}
    errors: dict[int, str] = {}
    m_max = max(usable)
    from tqdm.auto import tqdm  # (imported when used, as in optim.fit)

    off = None if progress is None else not progress
    for m in tqdm(usable, desc="embedding m", disable=off, leave=False):
        # the same validation targets z[split:] for every m; training targets from m_max on
        Xt, Yt = _pairs(z, m, m_max, split)
        Xv, Yv = _pairs(z, m, split, T)
        net = build_learner(learner, m, learner_options, seed=seed, device=z.device, n_rows=T)
        try:
            _closed_form(learner, net, Xt, Yt, learner_options)
            scores[m] = float(rmse(_predict(net, Xv), Yv))
        except MemoryBudgetError:
            raise
        except (RuntimeError, ValueError, torch.linalg.LinAlgError, MemoryError) as exc:
            scores[m] = math.inf  # incl. non-finite output (rmse raises)
            oom = allocation_failure(exc, learner)
            if oom is not None:
                raise MemoryBudgetError(f"fitting {learner.upper()} with m={m}: {oom}") from None
            errors[m] = " ".join(str(exc).split()) or type(exc).__name__
        if not math.isfinite(scores[m]):
            scores[m] = math.inf
            errors.setdefault(m, "non-finite validation predictions")
    best = min(scores, key=lambda k: (scores[k], k))
    if not math.isfinite(scores[best]):
        reasons = sorted(set(errors.values()))
        detail = reasons[0]
        if len(reasons) > 1:
            detail = "; ".join(f"m={k}: {v}" for k, v in errors.items())
        raise ValueError(
            f"no embedding dimension gave a finite validation error: {learner.upper()} failed "
            f"for every m in {usable} ({detail})"
        )
    return best, scores


def _kalman_options(name: str, learner: str, net: nn.Module, opts: dict) -> dict:
    P0, Q = opts["P0"], opts["Q"]
    if P0 is None:
        P0 = {"alpha": 1.0, "b": 1e-2, "beta": 1e-4} if learner == "anfis" else 1.0
    if Q is None:
        Q = 1e-6 if learner == "anfis" else 0.0
    kw = {"filter": name, "P0": P0, "Q": Q, "R": opts["R"]}
    if name == "imsrukf":
        est = tuple(opts["estimate"])
        kw["noise"] = SageHusa(estimate=est, diagonal=True)
    return kw


def _train(
    learner: str,
    optimizer: str,
    net: nn.Module,
    X: Tensor,
    Y: Tensor,
    lopts: dict,
    oopts: dict,
    seed: int,
    progress: bool | None = False,
) -> dict:
    """Train ``net`` in place; returns a small JSON-able record."""
    if optimizer == "closed-form":
        _closed_form(learner, net, X, Y, lopts)
        return {"epochs": 0}
    # iterative optimisers start from the learner's data-independent initialisation, except for
    # what the learner needs to exist at all: LS-SVR's support vectors, ANFIS premises
    if learner == "lssvr":
        net.fit(X, Y)
        with torch.no_grad():
            net.alpha.zero_()
            net.b.zero_()
    elif learner == "anfis":
        net.init_premises(X)
    epochs = oopts["epochs"]
    if not is_int(epochs) or epochs < 1:
        raise ValueError(f"epochs must be a positive int, got {epochs!r}")
    epochs = int(epochs)
    if "max_iter" in oopts:  # (LBFGS took max_iter=0 and trained nothing, unsaid)
        check_pos_int(oopts["max_iter"], f"{optimizer} optimizer option max_iter")
    if optimizer in KALMAN:
        n_state = sum(p.numel() for p in net.parameters() if p.requires_grad)
        if n_state > MAX_KALMAN_STATE:
            raise ValueError(
                f"{learner.upper()} with m={X.shape[1]} has {n_state} trainable parameters; a "
                f"Kalman optimiser keeps an {n_state} x {n_state} covariance and is refused above "
                f"{MAX_KALMAN_STATE} (use optimizer 'closed-form', 'adam' or 'lbfgs', a smaller "
                "m, or fewer rows)"
            )
        opt = KalmanOptimizer(net, **_kalman_options(optimizer, learner, net, oopts))
        hist = optim_fit(net, opt, (X, Y[:, None]), epochs=epochs, batch_size=1, progress=progress)
    elif not 0 < oopts["lr"] < math.inf:  # (torch said "Invalid learning rate: -1")
        raise ValueError(f"{optimizer} optimizer option lr must be a positive number, got "
                         f"{oopts['lr']!r}")  # fmt: skip
    elif optimizer == "adam":
        opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=oopts["lr"])
        hist = optim_fit(
            net, opt, (X, Y[:, None]), epochs=epochs, batch_size=X.shape[0], progress=progress
        )
    else:  # lbfgs
        opt = torch.optim.LBFGS(
            [p for p in net.parameters() if p.requires_grad],
            lr=oopts["lr"],
            max_iter=int(oopts["max_iter"]),
            line_search_fn="strong_wolfe",
        )
        hist = optim_fit(
            net, opt, (X, Y[:, None]), epochs=epochs, batch_size=X.shape[0], progress=progress
        )
    return {"epochs": len(hist.epoch)}


def _holdout_size(holdout, T: int) -> int:
    if isinstance(holdout, bool):
        raise ValueError(f"holdout must be a fraction in [0, 1) or a count, got {holdout!r}")
    if is_int(holdout):
        n = int(holdout)
        if n < 0:
            raise ValueError(f"holdout must be a fraction in [0, 1) or a count >= 0, got {n}")
    elif is_real(holdout) and 0.0 <= holdout < 1.0:
        n = int(round(float(holdout) * T))
    else:
        raise ValueError(f"holdout must be a fraction in [0, 1) or a count >= 0, got {holdout!r}")
    if n < 0 or n >= T:
        raise ValueError(f"holdout={holdout!r} leaves no training data in a series of {T} values")
    return n


def _training_size(series: Series, learner: str, m, holdout) -> tuple[int | None, int, int]:
    """``m`` (an int >= 1 or ``None``), the held-out count and the training count, with the
    refusals of a series too short for them (``ValueError`` naming ``m`` and the counts)."""
    T = len(series)
    if m is not None:
        if not is_int(m) or m < 1:
            raise ValueError(f"embedding dimension m must be a positive int, got {m!r}")
        m = int(m)
        if T < m + 1:
            raise ValueError(
                f"series {series.name!r} has {T} values; embedding m={m} needs at least "
                f"m + 1 = {m + 1} (one window and its next value)"
            )
    n_hold = _holdout_size(holdout, T)
    n_train = T - n_hold
    min_train = (m + 1) if m is not None else 2 * min(M_CANDIDATES[learner]) + 3
    if n_train < min_train or n_train < 3:
        raise ValueError(
            f"series {series.name!r} has {T} values, {n_train} after holding out {n_hold}: too "
            f"short to train (need at least {max(min_train, 3)}"
            + (f" for m={m})" if m is not None else " to choose m; or give m)")
        )
    if m is not None and n_train - m < m + 1:  # fewer windows than a linear map's m + 1 terms
        raise ValueError(
            f"series {series.name!r} has {n_train} training values: embedding m={m} leaves "
            f"{n_train - m} training window(s), fewer than the m + 1 = {m + 1} coefficients of "
            f"even a linear map on them; give m <= {(n_train - 1) // 2} (--embedding) or leave "
            "it out to have it chosen"
        )
    return m, n_hold, n_train


def fit_series(
    series: Series,
    learner: str = "anfis",
    optimizer: str | None = None,
    m: int | None = None,
    *,
    holdout: float | int = 0.2,
    seed: int = 0,
    learner_options: dict | None = None,
    optimizer_options: dict | None = None,
    data: dict | None = None,
    progress: bool | None = False,
    refit: bool = False,
) -> FittedModel:
    """Fit a one-step learner to ``series`` and evaluate it on the held-out tail.

    Args:
        series: the series (:func:`~prognos_torch.workflow.load_series`).
        learner: ``"elm"``, ``"lssvr"`` or ``"anfis"``.
        optimizer: ``None`` (the learner's default, see the module notes), ``"closed-form"``,
            ``"ekf"``, ``"srukf"``, ``"imsrukf"``, ``"adam"`` or ``"lbfgs"``.
        m: embedding dimension; ``None`` selects it by validation error.
        holdout: fraction in ``[0, 1)`` or number of final values kept for evaluation (0: none).
        seed: seeds the learner initialisation (and the default of later particle draws).
        learner_options: overrides of :data:`LEARNER_DEFAULTS` (e.g. ``{"n_hidden": 40}``).
        optimizer_options: overrides of :data:`OPTIMIZER_DEFAULTS` (e.g. ``{"epochs": 3}``).
        data: how the series was read (column, time column, where, fill), stored so that the
            command line can read the same column again.
        progress: ``tqdm`` bars on stderr over the embedding candidates and the training
            (``None``: only where stderr is a terminal; the command line's choice).
        refit: after scoring the held-out tail, train the returned model again on every value
            (the same ``m``, options and seed; its scaler from every value): the model to
            forecast the latest level with. Its ``metrics`` stay those of the scored model
            (``config["refit"]`` is ``True``; ``series.n_train`` counts every value).

    Returns:
        :class:`FittedModel`.
    """
    if not isinstance(series, Series):
        raise TypeError(f"series must be a Series (load_series(...)), got {type(series).__name__}")
    bad = (~torch.isfinite(series.values)).nonzero()[:, 0]
    if bad.numel():  # NaN (missing) or inf: a training window needs every value
        raise ValueError(
            f"series {series.name!r} has {bad.numel()} missing or non-finite value(s), the "
            f"first at row {int(bad[0])}: the learner's training windows need every value; fill "
            "or drop them (load_series(..., fill='linear' or 'drop'), --fill on the command line)"
        )
    learner, optimizer = check_names(learner, optimizer)
    lopts = _merge(LEARNER_DEFAULTS[learner], learner_options, f"{learner} learner")
    oopts = _merge(OPTIMIZER_DEFAULTS[optimizer], optimizer_options, f"{optimizer} optimizer")
    seed = check_seed(seed)
    refit = check_flag(refit, "refit")  # (np.bool_ too)
    if progress is not None:  # (read by its truth value: "no" drew the bars)
        progress = check_flag(progress, "progress")
    if data is not None and not isinstance(data, Mapping):  # (was found after the training)
        raise TypeError(f"data must be a dict or None, got {type(data).__name__}")
    m, n_hold, n_train = _training_size(series, learner, m, holdout)
    T = len(series)
    train = series.values[:n_train]
    scaler = MinMaxScaler((0.0, 1.0))
    try:
        scaler.fit(train)
    except ValueError:
        raise ValueError(
            f"series {series.name!r} is constant over its {n_train} training values; "
            "there is nothing to learn"
        ) from None
    z = scaler.transform(train)
    check_fit_memory(learner, optimizer, n_train, m or max(M_CANDIDATES[learner]), lopts)

    selection = None
    if m is None:
        t_sel = time.perf_counter()
        m, scores = select_embedding(
            z, learner, lopts, M_CANDIDATES[learner], seed=seed, progress=progress
        )
        selection = {
            "candidates": list(scores),
            "val_rmse": [None if not math.isfinite(v) else v for v in scores.values()],
            "criterion": "one-step validation RMSE on the last 20% of the training part",
            "seconds": time.perf_counter() - t_sel,  # (a fit per candidate: often the most)
        }
    X, Y = embed(z, m)
    net = build_learner(learner, m, lopts, seed=seed, device=z.device, n_rows=n_train)
    t0 = time.perf_counter()
    record = _train(learner, optimizer, net, X, Y, lopts, oopts, seed, progress)
    seconds = time.perf_counter() - t0
    net.eval()
    pred = _predict(net, X)
    if not all_finite(pred):
        raise ValueError(
            f"training {learner.upper()} with {optimizer} diverged (non-finite predictions); "
            "try another optimizer or options"
        )
    residual = float(rmse(pred, Y))
    config = {
        "learner": learner,
        "learner_options": lopts,
        "optimizer": optimizer,
        "optimizer_options": oopts,
        "m": m,
        "m_selection": selection,
        "scaler": {
            "data_min": float(scaler.data_min),
            "data_max": float(scaler.data_max),
            "feature_range": list(scaler.feature_range),
        },
        "dtype": "float64",
        "seed": seed,
        "residual_rmse": residual,
        "series": {
            "name": series.name,
            "time_name": series.time_name,
            "time_unit": series.time_unit,
            "start": series.start,
            "dt": series.dt,
            "n": T,
            "n_train": n_train,
            # the last training row's time (a backtest cut before it sees what it predicts)
            "t_train_end": float(series.t[n_train - 1]),
        },
        "data": dict(data or {}),
        "holdout": {"n": n_hold, "metrics": {}},
        "train": {"epochs": record["epochs"], "seconds": seconds, "train_rmse_scaled": residual},
    }
    if isinstance(net, FixedSizeLSSVR):
        config["train"]["support"] = {
            "kind": "fixed-size",
            "n_support": int(net.support_vectors.shape[0]),
            "selection": net.selection,
            "rank": net.rank,
        }
    model = FittedModel(net, scaler, config)
    if n_hold > 0:
        config["holdout"]["metrics"] = holdout_metrics(model, series, n_train)
    if refit and n_hold > 0:  # the scored model's metrics, every value's model
        full = fit_series(series, learner, optimizer, m, holdout=0, seed=seed,
                          learner_options=learner_options, optimizer_options=optimizer_options,
                          data=data, progress=progress)  # fmt: skip
        full.config["holdout"] = config["holdout"]
        full.config["m_selection"] = selection
        full.config["refit"] = True
        return full
    return model
