"""Training the learners of a forecaster matrix: every (learner, trainer) by name, ``R`` runs.

:func:`train_forecasters` trains ELM, LS-SVR or ANFIS one-step forecasters on a
:class:`~prognos_torch.studies.forecasters.ForecastProblem`'s windows with one of the trainers

* ``"closed"``: ELM ridge (paper 000 Eq. 52-54), LS-SVR KKT system (paper 002 Eq. 4);
* ``"EKF"``, ``"SRUKF"``, ``"ImSRUKF"``: one pass of a
  :class:`~prognos_torch.optim.KalmanOptimizer` (paper 003 Sec. IV);
* ``"Adam"``: mini-batch Adam (:func:`~prognos_torch.optim.fit`).

Run ``i`` draws its initialisation (ELM hidden layer, ANFIS consequents) from ``generator(i)``;
the runs come back as one :class:`~prognos_torch.optim.StackedLearner`. LS-SVR has no random
initialisation: its trainers start from the KKT solution and return one shared forecaster.
:func:`not_applicable` says which pairs do not apply (ANFIS has no closed form; the LS-SVR
Kalman state holds one dual weight per training window) and :func:`persistence` is the
reference forecaster ``x_{k+1} = x_k``. The settings are one record, :class:`MatrixTraining`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..learners import ANFIS, ELM, LSSVR, LSSVRGram
from ..optim import KalmanOptimizer, StackedLearner, fit, fit_kalman_runs, fit_together
from .forecasters import ForecastProblem

__all__ = [
    "KALMAN_TRAINERS",
    "MatrixTraining",
    "not_applicable",
    "persistence",
    "train_forecasters",
]

KALMAN_TRAINERS = ("EKF", "SRUKF", "ImSRUKF")
NA_REASONS = {
    "ANFIS-closed": "no closed form: the premise parameters enter nonlinearly",
    "LSSVR-Kalman": "Kalman state (alpha, b) with one entry per training window: too large",
}


@dataclass(frozen=True)
class MatrixTraining:
    """Learner and trainer settings of a forecaster matrix.

    Attributes:
        elm_hidden, elm_lam: ELM sigmoid nodes and ridge parameter.
        lssvr_sigma, lssvr_C: LS-SVR RBF width and regularisation.
        anfis_mfs: ANFIS sigmoid membership functions per input.
        kalman_R: measurement noise of the Kalman trainers; kalman_Q, kalman_P0: process noise
            and prior variances (per parameter group) per learner name.
        kalman_batch: samples per Kalman step, per problem name (one pass over the data).
        adam_lr: Adam learning rate; adam: ``(epochs, batch size)`` per problem name.
        lssvr_kalman_max: most training windows for which the LS-SVR Kalman trainers run.
    """

    elm_hidden: int
    elm_lam: float
    lssvr_sigma: float
    lssvr_C: float
    anfis_mfs: int
    kalman_R: float
    kalman_Q: Mapping[str, float]
    kalman_P0: Mapping[str, Mapping[str, float]]
    kalman_batch: Mapping[str, int]
    adam_lr: float
    adam: Mapping[str, tuple[int, int]]
    lssvr_kalman_max: int

    def config(self) -> dict:
        """The settings as the JSON record of a study's configuration."""
        return {
            "elm": {"hidden": self.elm_hidden, "lambda": self.elm_lam, "activation": "sigmoid"},
            "lssvr": {"kernel": "rbf", "sigma": self.lssvr_sigma, "C": self.lssvr_C},
            "anfis": {"mfs": self.anfis_mfs, "mf": "sigmoid"},
            "kalman": {
                "R": self.kalman_R,
                "Q": self.kalman_Q,
                "P0": self.kalman_P0,
                "batch": self.kalman_batch,
                "passes": 1,
            },
            "adam": {"lr": self.adam_lr, "epochs_batch": self.adam},
        }


def not_applicable(
    learner: str,
    trainer: str,
    problem: ForecastProblem,
    settings: MatrixTraining,
    reasons: Mapping[str, str] = NA_REASONS,
) -> str | None:
    """Why ``(learner, trainer)`` is not run on ``problem`` (``None``: it is).

    ``reasons["ANFIS-closed"]``: ANFIS has no closed form. ``reasons["LSSVR-Kalman"]``: a Kalman
    trainer of the LS-SVR when the problem has more than ``settings.lssvr_kalman_max`` training
    windows (its state ``(alpha, b)`` has one entry per window, plus one).
    """
    if learner == "ANFIS" and trainer == "closed":
        return reasons["ANFIS-closed"]
    too_many = problem.X.shape[0] > settings.lssvr_kalman_max
    if learner == "LSSVR" and trainer in KALMAN_TRAINERS and too_many:
        return reasons["LSSVR-Kalman"]
    return None


def persistence(x: Tensor) -> Tensor:
    """The reference forecaster ``x_{k+1} = x_k``: ``(..., m)`` windows -> ``(..., 1)``."""
    return x[..., -1:]


def train_forecasters(
    learner: str,
    trainer: str,
    problem: ForecastProblem,
    settings: MatrixTraining,
    *,
    runs: int,
    generator: Callable[[int], torch.Generator],
    device: str | torch.device = "cpu",
    shuffle_key: int = 2 * 10**6,
) -> nn.Module:
    """Train ``runs`` one-step forecasters ``(..., m) -> (..., 1)`` on ``problem.X, problem.Y``.

    Args:
        learner: ``"ELM"``, ``"LSSVR"`` or ``"ANFIS"``.
        trainer: ``"closed"``, ``"EKF"``, ``"SRUKF"``, ``"ImSRUKF"`` or ``"Adam"``.
        problem: the training windows ``X (N, m)`` and targets ``Y (N, 1)``.
        settings: the learner and trainer settings (:class:`MatrixTraining`).
        runs: Monte Carlo runs ``R``.
        generator: ``i -> torch.Generator`` of run ``i``'s initialisation; ``generator(
            shuffle_key)`` draws the Adam mini-batch order shared by the runs.

    Returns:
        A :class:`~prognos_torch.optim.StackedLearner` of ``R`` runs (runs leading: inputs
        ``(R, ..., m)``), or for the LS-SVR one deterministic
        :class:`~prognos_torch.learners.LSSVRGram` shared by every run.
    """
    X, Y, st = problem.X, problem.Y, settings
    if learner not in ("ELM", "LSSVR", "ANFIS"):
        raise ValueError(f"unknown learner {learner!r}; choose ELM, LSSVR or ANFIS")
    if trainer not in ("closed", *KALMAN_TRAINERS, "Adam"):
        raise ValueError(f"unknown trainer {trainer!r}; choose closed, EKF, SRUKF, ImSRUKF, Adam")
    kalman = dict(
        filter=trainer.lower(), P0=st.kalman_P0[learner], Q=st.kalman_Q[learner], R=st.kalman_R
    )
    # the ImSRUKF noise estimator needs equal mini-batches: it drops an incomplete last one
    kfit = dict(epochs=1, batch_size=st.kalman_batch[problem.name], drop_last=trainer == "ImSRUKF")
    kfit["progress"] = False
    epochs, bs = st.adam[problem.name]
    if learner == "LSSVR":  # deterministic: the KKT solution, shared by the runs
        mod = LSSVR(sigma=st.lssvr_sigma, C=st.lssvr_C).to(device).fit(X, Y)
        if trainer == "Adam":  # from the KKT solution, mini-batches in time order
            opt = torch.optim.Adam([p for p in mod.parameters() if p.requires_grad], lr=st.adam_lr)
            fit(mod, opt, (X, Y), epochs=epochs, batch_size=bs, progress=False)
        elif trainer != "closed":  # state (alpha, b), prior mean = the KKT solution
            fit(mod, KalmanOptimizer(mod, **kalman), (X, Y), **kfit)
        return LSSVRGram(mod)
    if learner == "ELM":
        mods = [
            ELM(problem.m, st.elm_hidden, generator=generator(i)).to(device) for i in range(runs)
        ]
    else:
        mods = [
            ANFIS(problem.m, st.anfis_mfs, generator=generator(i)).to(device).init_premises(X)
            for i in range(runs)
        ]
    if trainer == "closed":
        if learner == "ANFIS":
            raise ValueError("ANFIS has no closed form (see not_applicable)")
        return StackedLearner.from_modules([m.fit_ridge(X, Y, st.elm_lam) for m in mods])
    if trainer == "Adam":  # one optimiser over the runs: shuffled mini-batches shared by all
        adam = lambda ps: torch.optim.Adam(ps, lr=st.adam_lr)  # noqa: E731
        opts = dict(epochs=epochs, batch_size=bs, shuffle=True, generator=generator(shuffle_key))
        return fit_together(mods, adam, (X, Y), progress=False, **opts)
    # one Kalman optimiser for the ANFIS runs, one per ELM run (each has its own hidden layer)
    return fit_kalman_runs(mods, (X, Y), fit_options=kfit, **kalman)
