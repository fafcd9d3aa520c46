"""Memory budget of the workflow and the size policy of the LS-SVR on long series.

Before a large allocation (the ``N x N`` LS-SVR kernel matrix, an ELM or ANFIS design matrix,
the particle paths of a forecast) the workflow estimates the bytes and refuses with
:class:`MemoryBudgetError` (a ``ValueError``: the command line prints one line and exits with
status 2, nothing written) instead of being killed by the operating system. The message names
what to change: ``--max-support M`` (a fixed-size LS-SVR on ``M`` support points),
``--last N`` (fewer rows), ``--learner elm``, fewer ``--particles`` or a shorter ``--horizon``.

**Budget**: the environment variable ``PROGNOS_MEMORY_BUDGET`` (bytes, or with a unit:
``512M``, ``2G``, ``1.5GB``); by default half of the machine's physical memory. The estimates
cover the dominant tensors (the ones that grow with rows, support points or particles), not
the interpreter and torch themselves (a few hundred MB).

**LS-SVR size policy** (:func:`lssvr_support`): the exact LS-SVR (KKT solve of paper 002,
Eq. 4) up to :data:`FULL_LSSVR_MAX_ROWS` training values; above, the fixed-size LS-SVR
(:class:`~prognos_torch.learners.FixedSizeLSSVR`) on :data:`DEFAULT_SUPPORT` support points
chosen by quadratic Renyi entropy. The learner option ``max_support=M`` replaces both: the
exact LS-SVR up to ``M`` values, ``M`` support points above.
"""

from __future__ import annotations

import os
import re

from ..core.validation import is_int
from ..learners.lssvr import KERNEL_BLOCK_BYTES

__all__ = [
    "MemoryBudgetError",
    "ENV_BUDGET",
    "FULL_LSSVR_MAX_ROWS",
    "DEFAULT_SUPPORT",
    "memory_budget",
    "parse_bytes",
    "format_bytes",
    "lssvr_support",
    "fit_bytes",
    "check_fit_memory",
    "check_paths_memory",
    "check_prognose_memory",
    "check_forecast_memory",
    "PROGNOSE_VALUES_PER_PATH",
    "allocation_failure",
]

ENV_BUDGET = "PROGNOS_MEMORY_BUDGET"
#: Largest training part (values) fitted by the exact LS-SVR when ``max_support`` is not given.
FULL_LSSVR_MAX_ROWS = 2000
#: Support points of the fixed-size LS-SVR above :data:`FULL_LSSVR_MAX_ROWS`.
DEFAULT_SUPPORT = 50

_UNITS = {"": 1, "B": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}
_F64 = 8


class MemoryBudgetError(ValueError):
    """A request whose estimated memory exceeds the budget (:func:`memory_budget`)."""


def parse_bytes(text: str) -> int:
    """``"512M"``, ``"2G"``, ``"1.5GB"``, ``"1000000"`` -> bytes (binary units)."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMGT]?)(I?B)?\s*", str(text).upper())
    if m is None:
        raise ValueError(
            f"{ENV_BUDGET}={text!r}: expected bytes or a number with a unit, e.g. 512M or 2G"
        )
    value = float(m.group(1)) * _UNITS[m.group(2)]
    if not value >= 1:
        raise ValueError(f"{ENV_BUDGET}={text!r}: the budget must be at least 1 byte")
    return int(value)


def format_bytes(n: float) -> str:
    """Bytes in a short human form (``1.5 GB``; binary units)."""
    for unit, size in (("TB", 2**40), ("GB", 2**30), ("MB", 2**20), ("kB", 2**10)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} B"


def memory_budget() -> int:
    """Bytes the workflow may allocate: ``PROGNOS_MEMORY_BUDGET`` or half the physical memory."""
    text = os.environ.get(ENV_BUDGET)
    if text is not None and text.strip():
        return parse_bytes(text)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 8 * 2**30


def lssvr_support(n_rows: int, max_support: int | None) -> int | None:
    """Support points of the LS-SVR for ``n_rows`` training values: ``None`` for the exact
    LS-SVR (all rows), else ``M`` for the fixed-size LS-SVR (module notes)."""
    if max_support is not None and (not is_int(max_support) or max_support < 1):
        raise ValueError(f"max_support must be a positive int or None, got {max_support!r}")
    max_support = None if max_support is None else int(max_support)
    limit = FULL_LSSVR_MAX_ROWS if max_support is None else max_support
    if n_rows <= limit:
        return None
    return DEFAULT_SUPPORT if max_support is None else max_support


def fit_bytes(learner: str, optimizer: str, n_rows: int, m: int, options: dict) -> tuple[int, str]:
    """Estimated peak bytes of fitting ``learner`` on ``n_rows`` windows of size ``m``, and a
    description of the dominant allocation."""
    base = _F64 * n_rows * (3 * m + 8)  # series, windows, targets and predictions
    if learner == "lssvr":
        M = lssvr_support(n_rows, options.get("max_support"))
        if M is None:  # Omega, Omega + I / C and its Cholesky factor (Eq. 4)
            return base + 3 * _F64 * n_rows**2 + KERNEL_BLOCK_BYTES, (
                f"the exact LS-SVR's {n_rows:,} x {n_rows:,} kernel matrix"
            )
        # K_MM, its eigenvectors, W and the triangular factor; blocks of kernel rows
        return base + 6 * _F64 * M * M + 4 * KERNEL_BLOCK_BYTES, (
            f"the fixed-size LS-SVR's {M:,} x {M:,} support-point matrices"
        )
    if learner == "elm":  # hidden-layer matrix H (Eq. 51) and its products
        L = int(options.get("n_hidden", 20))
        return base + 3 * _F64 * n_rows * L, f"the ELM's {n_rows:,} x {L} hidden-layer matrix"
    if learner == "anfis":  # regressor matrix V (N, rules (m + 1)) and its SVD
        rules = int(options.get("n_mfs", 2)) ** m
        P = rules * (m + 1)
        per = 3 * P if optimizer == "closed-form" else 2 * P
        return base + _F64 * n_rows * per, (
            f"the ANFIS {n_rows:,} x {P:,} regressor matrix ({rules:,} rules)"
        )
    return base, f"{n_rows:,} windows"


def _hint(learner: str) -> str:
    if learner == "lssvr":
        return (
            "use --max-support M (a fixed-size LS-SVR on M support points; learner option "
            "max_support), --last N (fewer rows) or --learner elm"
        )
    if learner == "elm":  # (its hidden layer, n_hidden, sets the memory per row)
        return "use --last N (fewer rows), a smaller --embedding or fewer hidden nodes (n_hidden)"
    if learner == "anfis":  # (its rules, n_mfs ** m, set the parameter count)
        return (
            "use a smaller --embedding or fewer membership functions (n_mfs): the rules, "
            "n_mfs ** m, set the parameters; --last N (fewer rows) or --learner elm"
        )
    return "use --last N (fewer rows), a smaller --embedding, or --learner elm"


def check_fit_memory(learner: str, optimizer: str, n_rows: int, m: int, options: dict) -> int:
    """Raise :class:`MemoryBudgetError` when fitting would exceed the budget; returns the
    estimate (bytes)."""
    need, what = fit_bytes(learner, optimizer, n_rows, m, options)
    budget = memory_budget()
    if need > budget:
        raise MemoryBudgetError(
            f"fitting {learner.upper()} on {n_rows:,} rows with m={m} needs about "
            f"{format_bytes(need)} ({what}), more than the memory budget of "
            f"{format_bytes(budget)} ({ENV_BUDGET}); {_hint(learner)}"
        )
    return need


def _within_budget(need: int, what: str, remedy: str) -> int:
    """``need`` bytes, or a :class:`MemoryBudgetError` saying that ``what`` ("... need") needs
    more than the budget, and ``remedy``."""
    budget = memory_budget()
    if need > budget:
        raise MemoryBudgetError(
            f"{what} about {format_bytes(need)}, more than the memory budget of "
            f"{format_bytes(budget)} ({ENV_BUDGET}); {remedy}"
        )
    return need


def check_paths_memory(n_particles: int, horizon: int, m: int) -> int:
    """Raise :class:`MemoryBudgetError` when ``n_particles`` paths of ``horizon`` steps (and
    the filter's per-particle covariances) would exceed the budget; returns the estimate."""
    need = _F64 * n_particles * (6 * horizon + 4 * m * m + 8 * m) + KERNEL_BLOCK_BYTES
    return _within_budget(need, f"{n_particles:,} particle paths of {horizon:,} steps need",
                          "use fewer --particles or a shorter --horizon")  # fmt: skip


#: Memory per step of a Gaussian-filter forecast, in float64 values: measured about 7 kB a
#: step (peak resident memory of a 100,000-step ELM forecast), rounded up.
FORECAST_VALUES_PER_STEP = 1024


def check_forecast_memory(horizon: int) -> int:
    """Raise :class:`MemoryBudgetError` when a Gaussian-filter forecast of ``horizon`` steps
    would exceed the budget (:data:`FORECAST_VALUES_PER_STEP` each); returns the estimate."""
    need = _F64 * horizon * FORECAST_VALUES_PER_STEP + KERNEL_BLOCK_BYTES
    return _within_budget(need, f"a forecast of {horizon:,} steps needs",
                          "use a shorter --horizon")  # fmt: skip


#: Memory per ``prognose`` sample path, in float64 values: measured 3.8 kB a path (peak
#: resident memory, 2,000 against 400,000 paths of the default ``auto`` pool), rounded up.
PROGNOSE_VALUES_PER_PATH = 512


def check_prognose_memory(n_paths: int) -> int:
    """Raise :class:`MemoryBudgetError` when ``prognose``'s ``n_paths`` sample paths would
    exceed the budget (:data:`PROGNOSE_VALUES_PER_PATH` each); returns the estimate."""
    need = _F64 * n_paths * PROGNOSE_VALUES_PER_PATH + KERNEL_BLOCK_BYTES
    return _within_budget(need, f"n_paths = {n_paths:,} sample paths need",
                          "use fewer paths (--paths)")  # fmt: skip


def allocation_failure(exc: BaseException, learner: str) -> str | None:
    """A one-line explanation when ``exc`` is a failed allocation (``MemoryError``, torch's
    "can't allocate memory" / out-of-memory errors), else ``None``."""
    text = str(exc)
    if isinstance(exc, MemoryError) or (
        isinstance(exc, RuntimeError)
        and ("allocate" in text.lower() or "out of memory" in text.lower())
    ):
        first = " ".join(text.split())[:160] or type(exc).__name__
        return f"out of memory ({first}); {_hint(learner)}"
    return None
