"""The filters of the library as configurations of the two engines, by name.

Gaussian filters are :class:`~prognos_torch.filters.gaussian.GaussianFilter` configurations (a
moment rule, the covariance algebra, adaptation pieces); particle filters are
:class:`~prognos_torch.filters.particle.ParticleFilter` configurations (a proposal, resampling).
A new variant is a new factory here, never a copy of a step.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from torch import Tensor

from ..adapt.noise import MovingWindow, SageHusa
from ..adapt.robust import RobustBound
from ..adapt.strong_tracking import StrongTracking
from ..core.validation import check_flag, check_setting
from ..quadrature import SigmaPoints, cubature, julier, unscented
from .gaussian import GaussianFilter, Taylor
from .particle import ParticleFilter

__all__ = [
    "ekf",
    "ukf",
    "srukf",
    "ckf",
    "sckf",
    "stekf",
    "stukf",
    "stsckf",
    "imsrukf",
    "rukf",
    "arukf",
    "make_filter",
    "FILTERS",
    "sir",
    "ekpf",
    "upf",
    "stpf",
    "PARTICLE_FILTERS",
    "make_particle_filter",
]


# ---------------------------------------------------------------------- Gaussian filters
def ekf(*, sqrt: bool = True, **kw) -> GaussianFilter:
    """Extended Kalman filter (Jacobians by ``torch.func``)."""
    return GaussianFilter(Taylor(), sqrt=check_flag(sqrt, "sqrt"), name=kw.pop("name", "EKF"), **kw)


def ukf(
    alpha: float = 1.0, beta: float = 2.0, kappa: float | None = 0.0, *, sqrt: bool = False, **kw
) -> GaussianFilter:
    """Unscented KF with the scaled rule (full covariance algebra by default)."""
    # (unscented() takes float(alpha): text failed with float()'s message, True became 1.0)
    check_setting(alpha, "alpha")
    check_setting(beta, "beta")
    return GaussianFilter(
        unscented(alpha, beta, kappa),
        sqrt=check_flag(sqrt, "sqrt"),
        name=kw.pop("name", "UKF"),
        **kw,
    )


def srukf(kappa: float | None = 1.0, *, rule: SigmaPoints | None = None, **kw) -> GaussianFilter:
    """Square-root UKF of paper 003 (Eq. 10-30), Julier's rule with ``kappa = 1`` by default;
    ``rule`` replaces Julier's rule (``kappa`` is then the rule's own, not an option here)."""
    if rule is not None and kappa != 1.0:
        raise ValueError(f"give kappa or rule, not both: kappa={kappa!r} would be ignored")
    return GaussianFilter(rule or julier(kappa), sqrt=True, name=kw.pop("name", "SRUKF"), **kw)


def ckf(**kw) -> GaussianFilter:
    """Cubature KF (full covariance algebra)."""
    return GaussianFilter(cubature(), sqrt=False, name=kw.pop("name", "CKF"), **kw)


def sckf(**kw) -> GaussianFilter:
    """Square-root cubature KF (paper 000 Eq. 21-46 without fading)."""
    return GaussianFilter(cubature(), sqrt=True, name=kw.pop("name", "SCKF"), **kw)


def stekf(rho: float = 0.95, beta: float = 1.0, **kw) -> GaussianFilter:
    """Strong-tracking EKF / SFEKF (paper 000 Eq. 7-12)."""
    return ekf(fading=StrongTracking(rho, beta), name=kw.pop("name", "STEKF"), **kw)


def stukf(
    rho: float = 0.95, beta: float = 1.0, kappa: float | None = 1.0, *, sqrt: bool = True, **kw
) -> GaussianFilter:
    """Strong-tracking UKF: the derivative-free fading factor (paper 000 Eq. 27-36) on Julier's
    rule (paper 003 Eq. 12-13, ``kappa=None``: ``3 - n``).

    ``sqrt=True``: the SRUKF's square-root algebra (a negative ``W_0`` enters as a Cholesky
    downdate, paper 003 Eq. 17); ``sqrt=False``: full covariances
    (``P = lambda (sum_i W_i d_i d_i^T) + Q`` with ``W_0 < 0`` subtracted directly), the form of
    a textbook UKF with ``kappa = 3 - n``.
    """
    return GaussianFilter(
        julier(kappa),
        sqrt=check_flag(sqrt, "sqrt"),
        fading=StrongTracking(rho, beta),
        name=kw.pop("name", "STUKF"),
        **kw,
    )


def stsckf(rho: float = 0.95, beta: float = 1.0, **kw) -> GaussianFilter:
    """Strong-tracking square-root cubature KF (paper 000 Sec. 3.3, Eq. 21-46)."""
    return sckf(fading=StrongTracking(rho, beta), name=kw.pop("name", "STSCKF"), **kw)


def imsrukf(kappa: float | None = 1.0, *, noise: SageHusa | None = None, **kw) -> GaussianFilter:
    """ImSRUKF: SRUKF with the Sage-Husa noise-statistics estimator (paper 003 Sec. III-B)."""
    if noise is not None and not isinstance(noise, SageHusa):
        # (the engine would fail at the first step with an AttributeError)
        raise TypeError(f"noise must be a SageHusa estimator or None, got {type(noise).__name__}")
    return srukf(kappa, noise=noise or SageHusa(), name=kw.pop("name", "ImSRUKF"), **kw)


def rukf(
    gamma: float,
    M: Tensor,
    N: float | Tensor = 1.0,
    *,
    alpha: float = 1.0,
    kappa: float = 1.0,
    form: str = "scalar",
    bound: str = "printed",
    **kw,
) -> GaussianFilter:
    """Robust UKF of paper 004 (Theorem 1, steps 1-5): sigma points of Eq. 36, gain Eq. 29.

    Paper 004 Eq. 36 uses ``xi = x +- a sqrt((n + 1) P)``, i.e. the scaled rule with
    ``alpha = a`` and ``kappa = 1``. ``form``: the reading of the bound (see
    :class:`~prognos_torch.adapt.robust.RobustBound`; ``"scalar"`` is Eq. 28-29 as printed).
    ``bound``: ``"printed"`` (the scale fixed by ``gamma``) or ``"optimised"`` (the scale of
    Eq. 28's bound chosen per step to minimise ``trace P_k``; ``form="scalar"`` only).
    """
    check_setting(alpha, "alpha")  # (unscented() takes float(alpha))
    return GaussianFilter(
        unscented(alpha, 0.0, kappa),
        sqrt=check_flag(kw.pop("sqrt", True), "sqrt"),
        robust=RobustBound(gamma, M, N, form=form, bound=bound),
        name=kw.pop("name", "RUKF"),
        **kw,
    )


def arukf(
    gamma: float,
    M: Tensor,
    N: float | Tensor = 1.0,
    *,
    window: int = 50,
    diagonal: bool = True,
    form: str = "scalar",
    bound: str = "printed",
    **kw,
) -> GaussianFilter:
    """Adaptive robust UKF of paper 004 (Sec. 3): RUKF + moving-window Q/R estimator (Eq. 47-49).

    With ``form="lemma"`` the innovation covariance is matched against ``C P~ C^T + gamma^2 M M^T``
    (``P~`` already holds the ``N`` bound); with ``"scalar"`` against Eq. 48 as printed
    (``(1 - N^2 / mu) C P C^T + mu M M^T``, ``mu = gamma^2``; also with ``bound="optimised"``,
    which changes only the bound of Eq. 60, see :func:`rukf`).
    """
    # the bound's checks first (gamma**2 and float(N) below failed with Python's messages on a
    # text gamma or a matrix N); its gamma is a float (a NumPy float32 squared in float32 moved
    # mu = gamma^2 by 1e-7 relative)
    rob = RobustBound(gamma, M, N, form=form, bound=bound)
    if not (math.isfinite(rob.gamma) and rob.gamma > 0):  # (bound="optimised" leaves gamma free)
        raise ValueError(
            f"gamma must be a positive finite number (mu = gamma^2 of Eq. 48), got {gamma!r}"
        )
    diagonal = check_flag(diagonal, "diagonal")
    mu = rob.gamma**2
    if form == "lemma":
        est = MovingWindow(window=window, M=M, N=0.0, mu=mu, diagonal=diagonal)
    else:
        est = MovingWindow(window=window, M=M, N=rob.N, mu=mu, diagonal=diagonal)
    return rukf(gamma, M, N, form=form, bound=bound, noise=est, name=kw.pop("name", "ARUKF"), **kw)


FILTERS = {
    "ekf": ekf,
    "ukf": ukf,
    "srukf": srukf,
    "ckf": ckf,
    "sckf": sckf,
    "stekf": stekf,
    "stukf": stukf,
    "stsckf": stsckf,
    "imsrukf": imsrukf,
}


#: the robust filters of paper 004 by name: they need the bound's ``gamma`` and ``M``, so they
#: are not among :data:`FILTERS` (the filters that build without settings, which ``prognose``,
#: the command line and the studies offer by name)
_ROBUST_FILTERS = {"rukf": rukf, "arukf": arukf}


def make_filter(name: str, **kw) -> GaussianFilter:
    """Build a configured filter by name (``ekf``, ``ukf``, ``srukf``, ``ckf``, ``sckf``,
    ``stekf``, ``stukf``, ``stsckf``, ``imsrukf``; ``rukf`` and ``arukf`` with the robust
    bound's ``gamma`` and ``M``: ``make_filter("rukf", gamma=3.0, M=M)``)."""
    if not isinstance(name, str):
        raise TypeError(f"name must be a filter name (str), got {type(name).__name__}")
    key = name.lower()
    make = FILTERS.get(key) or _ROBUST_FILTERS.get(key)
    if make is None:
        raise ValueError(
            f"unknown filter {name!r}; choose one of {sorted(FILTERS | _ROBUST_FILTERS)}"
        )
    if key in _ROBUST_FILTERS and not {"gamma", "M"} <= kw.keys():
        raise TypeError(
            f"make_filter({name!r}) needs the robust bound's gamma and M (paper 004 Eq. 28), "
            f"e.g. make_filter({name!r}, gamma=3.0, M=M); got the options {sorted(kw)}"
        )
    return make(**kw)


# ---------------------------------------------------------------------- particle filters
def sir(num_particles: int = 1000, **kw) -> ParticleFilter:
    """Bootstrap (SIR) particle filter: transition prior as proposal."""
    return ParticleFilter(num_particles, None, name=kw.pop("name", "PF"), **kw)


def ekpf(
    num_particles: int = 1000, *, proposal: GaussianFilter | None = None, **kw
) -> ParticleFilter:
    """Extended Kalman particle filter: a per-particle EKF step as proposal."""
    return ParticleFilter(num_particles, proposal or ekf(), name=kw.pop("name", "EKPF"), **kw)


def upf(
    num_particles: int = 1000, *, proposal: GaussianFilter | None = None, **kw
) -> ParticleFilter:
    """Unscented particle filter (Van der Merwe et al. 2000): a per-particle UKF step as proposal
    (scaled rule ``alpha=1, beta=2, kappa=0``, square-root algebra, by default)."""
    prop = proposal or ukf(1.0, 2.0, 0.0, sqrt=True)
    return ParticleFilter(num_particles, prop, name=kw.pop("name", "UPF"), **kw)


def stpf(
    num_particles: int = 1000,
    rho: float = 0.95,
    beta: float = 1.0,
    *,
    resample_threshold: float = 1.0 / 3.0,
    **kw,
) -> ParticleFilter:
    """Strong-tracking particle filter of paper 002 (Eq. 27, steps 1-7): a per-particle SFEKF
    (strong-tracking EKF, paper 000 Eq. 7-12, forgetting ``rho``, weakening ``beta``) step as
    proposal; resampling when ``N_eff < N/3`` (step 6)."""
    return ParticleFilter(
        num_particles,
        stekf(rho, beta),
        resample_threshold=resample_threshold,
        name=kw.pop("name", "STPF"),
        **kw,
    )


PARTICLE_FILTERS: dict[str, Callable[..., ParticleFilter]] = {
    "sir": sir,
    "pf": sir,
    "ekpf": ekpf,
    "upf": upf,
    "stpf": stpf,
}


def make_particle_filter(name: str, **kw) -> ParticleFilter:
    """Build a particle filter by name (``sir``/``pf``, ``ekpf``, ``upf``, ``stpf``)."""
    if not isinstance(name, str):
        raise TypeError(f"name must be a particle filter name (str), got {type(name).__name__}")
    key = name.lower()
    if key not in PARTICLE_FILTERS:
        raise ValueError(
            f"unknown particle filter {name!r}; choose one of {sorted(PARTICLE_FILTERS)}"
        )
    return PARTICLE_FILTERS[key](**kw)
