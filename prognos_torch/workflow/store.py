"""Save and load a :class:`~prognos_torch.workflow.FittedModel` as a safe model file.

The file (:mod:`prognos_torch.io`, safetensors format) holds the learner's ``state_dict``
tensors (float64, raw bytes, names prefixed ``learner.``) and, in its metadata, the
configuration as JSON: learner, optimiser, their options, the embedding
dimension, the scaler range, the dtype, the seed, the fit record and the library version.
Loading parses JSON and copies bytes, never unpickles, and rebuilds the learner from the
configuration; a model loaded in a new process forecasts bit-identically (same thread count).
"""

from __future__ import annotations

import os

import torch

from ..core.validation import check_seed, is_int
from ..datasets.windows import MinMaxScaler
from ..io import ModelFileError, load_model_file, save_model_file
from .fitted import FittedModel
from .model import LEARNERS, build_learner

__all__ = ["save_model", "load_model", "MODEL_KIND"]

MODEL_KIND = "prognos-workflow"
_PREFIX = "learner."


def save_model(model: FittedModel, path: str | os.PathLike) -> None:
    """Write ``model`` to ``path`` (atomically; see :mod:`prognos_torch.io`).

    Raises:
        TypeError: a learner tensor that is not float64 (the file's ``dtype``; loading would
            widen it).
        ValueError: a learner tensor holding NaN or inf.
    """
    if not isinstance(model, FittedModel):
        raise TypeError(f"model must be a FittedModel, got {type(model).__name__}")
    tensors = {_PREFIX + k: v for k, v in model.learner.state_dict().items()}
    for name, t in tensors.items():  # what load_model refuses is not written
        if t.is_floating_point() and t.dtype != torch.float64:
            raise TypeError(
                f"model.learner's {name!r} is {t.dtype}; a model file holds the workflow's "
                "float64 learner (loading would silently widen it): save a float64 learner "
                "(model.learner.double())"
            )
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise ValueError(f"model.learner's {name!r} holds NaN or inf: not a fitted model")
    save_model_file(path, model.config, tensors, kind=MODEL_KIND)


def _need(config: dict, key: str, types, path) -> object:
    value = config.get(key)
    if isinstance(value, bool) or not isinstance(value, types):
        raise ModelFileError(f"{path}: configuration entry {key!r} is missing or malformed")
    return value


def _check_sizes(learner: str, m: int, lopts: dict, state: dict, path) -> None:
    """The sizes the configuration gives the learner match its stored tensors, checked before
    the learner is built (an edited ``n_hidden=10**9`` would allocate terabytes first)."""
    key = {"elm": "n_hidden", "anfis": "n_mfs"}.get(learner)
    n = lopts.get(key) if key else None
    if key and (not is_int(n) or n < 1):
        raise ModelFileError(
            f"{path}: configuration entry 'learner_options' has {key}={n!r}; expected a "
            "positive int"
        )
    name = {"elm": "a", "lssvr": "support_vectors", "anfis": "alpha"}[learner]
    t = state.get(name)
    if t is None:
        raise ModelFileError(f"{path}: the file has no tensor {_PREFIX + name!r}")
    shape = list(t.shape)
    if learner == "elm":
        want, what = [n, m], f"[n_hidden, m] = [{n}, {m}]"
    elif learner == "lssvr":
        want, what = [shape[0] if len(shape) == 2 else "n_support", m], f"[n_support, m={m}]"
    else:  # n_mfs ** m rules (Eq. 3), evaluated only where it cannot exceed the stored count
        rules = shape[-1] if len(shape) == 3 else 0
        small = n == 1 or m <= max(rules, 1).bit_length()
        want = [1, m + 1, n**m if small else None]
        what = f"[1, m + 1, n_mfs ** m] = [1, {m + 1}, {n}**{m}]"
    if shape != want:
        raise ModelFileError(
            f"{path}: the stored learner does not match its configuration (tensor "
            f"{_PREFIX + name!r} has shape {shape}; the configuration gives {what})"
        )


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (load_state_dict lists its findings line by line)."""
    if isinstance(exc, KeyError):
        return f"missing entry {exc.args[0]!r}" if exc.args else "missing entry"
    return " ".join(str(exc).split()) or type(exc).__name__


def load_model(path: str | os.PathLike, *, map_location: str | torch.device = "cpu") -> FittedModel:
    """Load a model written by :func:`save_model`.

    Raises:
        FileNotFoundError: no such file.
        ModelFileError: not a model file, corrupted or truncated, tampered (checksum), written by
            an incompatible version, a configuration that does not match its tensors (sizes
            checked before the learner is built, dtypes, names, one window through it), a
            tensor outside the learner or holding NaN/inf.
    """
    mf = load_model_file(path, kind=MODEL_KIND, map_location=map_location)
    cfg = mf.config
    learner = _need(cfg, "learner", str, path)
    if learner not in LEARNERS:
        raise ModelFileError(f"{path}: unknown learner {learner!r} in the configuration")
    m = _need(cfg, "m", int, path)
    if m < 1:
        raise ModelFileError(f"{path}: embedding dimension m={m} in the configuration")
    lopts = _need(cfg, "learner_options", dict, path)
    seed = _need(cfg, "seed", int, path)
    try:
        check_seed(seed)
    except ValueError as exc:
        raise ModelFileError(f"{path}: configuration entry 'seed': {exc}") from None
    rmse = _need(cfg, "residual_rmse", (int, float), path)
    if not 0 <= rmse < 1e3:  # (in scaled units, [0, 1]: a noise std far beyond it is no fit)
        raise ModelFileError(
            f"{path}: configuration entry 'residual_rmse' is {rmse!r}; a fit's residual RMSE "
            "in scaled units lies in [0, 1e3)"
        )
    if cfg.get("dtype") != "float64":
        raise ModelFileError(f"{path}: dtype {cfg.get('dtype')!r}; this version writes float64")
    sc = _need(cfg, "scaler", dict, path)
    series = cfg.get("series")
    if series is not None and not isinstance(series, dict):
        raise ModelFileError(f"{path}: configuration entry 'series' is missing or malformed")
    extra = sorted(k for k in mf.tensors if not k.startswith(_PREFIX))
    if extra:
        raise ModelFileError(
            f"{path}: unexpected tensor(s) {extra}; a workflow model file holds only the "
            f"learner's ({_PREFIX}*)"
        )
    state = {k[len(_PREFIX) :]: v for k, v in mf.tensors.items()}
    for k, v in state.items():
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise ModelFileError(f"{path}: tensor {_PREFIX + k!r} holds NaN or inf")
    _check_sizes(learner, m, lopts, state, path)
    try:
        n_train = (series or {}).get("n_train")  # the LS-SVR's size policy
        net = build_learner(learner, m, lopts, seed=seed, device=map_location, n_rows=n_train)
        expected = net.state_dict()
        for k, v in state.items():
            if k in expected and v.dtype != expected[k].dtype:
                raise ValueError(
                    f"tensor {_PREFIX + k!r} is {v.dtype}, the {learner.upper()} holds "
                    f"{expected[k].dtype}"
                )
        net.load_state_dict(state, strict=True)
    except (RuntimeError, ValueError, TypeError, KeyError) as exc:
        raise ModelFileError(
            f"{path}: the stored learner does not match its configuration ({_one_line(exc)})"
        ) from None
    try:
        scaler = MinMaxScaler()
        scaler.load_state_dict(
            {
                "data_min": torch.tensor(float(sc["data_min"]), dtype=torch.float64),
                "data_max": torch.tensor(float(sc["data_max"]), dtype=torch.float64),
                "feature_range": tuple(sc["feature_range"]),
            }
        )
    except (RuntimeError, ValueError, TypeError, KeyError) as exc:
        raise ModelFileError(
            f"{path}: configuration entry 'scaler' is malformed ({_one_line(exc)})"
        ) from None
    try:  # one window through the learner: the stored sizes agree (LS-SVR's are data-sized)
        dev = next(iter(net.parameters())).device
        with torch.no_grad():
            out = net(torch.full((1, m), 0.5, dtype=torch.float64, device=dev))
        if tuple(out.shape) != (1, 1):
            raise ValueError(f"a (1, {m}) window gives an output of shape {tuple(out.shape)}")
    except (RuntimeError, ValueError, TypeError, IndexError) as exc:
        raise ModelFileError(
            f"{path}: the stored learner does not match its configuration ({_one_line(exc)})"
        ) from None
    net.eval()
    return FittedModel(net, scaler, dict(cfg))
