"""Fleets: RUL for many assets from one long table, batched, sharded, local or on Ray.

* :func:`fleet_rul` - a table (asset, time, value columns) in, one row per asset out: ``asset,
  n_rows, t_last, onset_time, rul_median, rul_q05, rul_q95, p_fail_within_horizon,
  censored_mass, flags, message``;
* :func:`read_fleet_table` / :func:`write_table` - CSV built in, pandas and Parquet through the
  ``tables`` extra; output written atomically;
* :func:`exponential_trend_rul` - the batched RUL method (onset, exponential trend by the
  engine, posterior sampling per asset); :func:`prognose_rul` - the workflow's ``prognose`` per
  asset (``method="prognose"``);
* :func:`calibrate_fleet` - the fleet's 90 % intervals calibrated on its failed assets (split
  conformal, replayed through one ``fleet_rul`` call), applied by ``FleetResult.calibrated``;
* :func:`synthetic_fleet` - exponential degradation with known failure times, for tests and
  benchmarks.
"""

from .batch import PaddedBatch, asset_seed, ksigma_onset_batch, pad_batch
from .calibrate import calibrate_fleet
from .per_asset import prognose_rul
from .run import DATE_COLUMNS, METHODS, OUTPUT_COLUMNS, FleetResult, fleet_rul, run_shard
from .synthetic import SyntheticFleet, synthetic_fleet
from .table import TABLE_SUFFIXES, FleetTable, read_fleet_table, write_table
from .trend import MISFIT_P, RUL_COLUMNS, exponential_trend_rul

__all__ = [
    "FleetResult",
    "FleetTable",
    "METHODS",
    "MISFIT_P",
    "OUTPUT_COLUMNS",
    "DATE_COLUMNS",
    "PaddedBatch",
    "RUL_COLUMNS",
    "SyntheticFleet",
    "TABLE_SUFFIXES",
    "asset_seed",
    "calibrate_fleet",
    "exponential_trend_rul",
    "fleet_rul",
    "ksigma_onset_batch",
    "pad_batch",
    "prognose_rul",
    "read_fleet_table",
    "run_shard",
    "synthetic_fleet",
    "write_table",
]
