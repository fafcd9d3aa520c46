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

from ..datasets.windows import MinMaxScaler
from ..io import ModelFileError, load_model_file, save_model_file
from .fitted import FittedModel
from .model import LEARNERS, build_learner

__all__ = ["save_model", "load_model", "MODEL_KIND"]

MODEL_KIND = "prognos-workflow"
_PREFIX = "learner."


def save_model(model: FittedModel, path: str | os.PathLike) -> None:
    """Write ``model`` to ``path`` (atomically; see :mod:`prognos_torch.io`)."""
    if not isinstance(model, FittedModel):
        raise TypeError(f"model must be a FittedModel, got {type(model).__name__}")
    tensors = {_PREFIX + k: v for k, v in model.learner.state_dict().items()}
    save_model_file(path, model.config, tensors, kind=MODEL_KIND)


def _need(config: dict, key: str, types, path) -> object:
    value = config.get(key)
    if isinstance(value, bool) or not isinstance(value, types):
        raise ModelFileError(f"{path}: configuration entry {key!r} is missing or malformed")
    return value


def load_model(path: str | os.PathLike, *, map_location: str | torch.device = "cpu") -> FittedModel:
    """Load a model written by :func:`save_model`.

    Raises:
        FileNotFoundError: no such file.
        ModelFileError: not a model file, corrupted or truncated, tampered (checksum), written by
            an incompatible version, or a configuration that does not match its tensors.
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
    rmse = _need(cfg, "residual_rmse", (int, float), path)
    if not 0 <= rmse < 1e3:  # (in scaled units, [0, 1]: a noise std far beyond it is no fit)
        raise ModelFileError(
            f"{path}: configuration entry 'residual_rmse' is {rmse!r}; a fit's residual RMSE "
            "in scaled units lies in [0, 1e3)"
        )
    if cfg.get("dtype") != "float64":
        raise ModelFileError(f"{path}: dtype {cfg.get('dtype')!r}; this version writes float64")
    sc = _need(cfg, "scaler", dict, path)
    state = {k[len(_PREFIX) :]: v for k, v in mf.tensors.items() if k.startswith(_PREFIX)}
    try:
        n_train = (cfg.get("series") or {}).get("n_train")  # the LS-SVR's size policy
        net = build_learner(learner, m, lopts, seed=seed, device=map_location, n_rows=n_train)
        net.load_state_dict(state, strict=True)
        scaler = MinMaxScaler()
        scaler.load_state_dict(
            {
                "data_min": torch.tensor(float(sc["data_min"]), dtype=torch.float64),
                "data_max": torch.tensor(float(sc["data_max"]), dtype=torch.float64),
                "feature_range": tuple(sc["feature_range"]),
            }
        )
    except (RuntimeError, ValueError, TypeError, KeyError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ModelFileError(
            f"{path}: the stored learner does not match its configuration ({msg})"
        ) from None
    net.eval()
    return FittedModel(net, scaler, dict(cfg))
