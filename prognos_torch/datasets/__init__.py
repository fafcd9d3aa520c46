"""Data for the prognostic studies: NASA IMS bearing features, LLE, windows and scaling.

* :mod:`.ims`: raw IMS snapshot reader, the shipped feature table, paper 002's health indicator.
* :mod:`.pronostia`: reader of the PRONOSTIA (FEMTO, IEEE PHM 2012) bearing records (not shipped).
* :mod:`.lle`: locally linear embedding (Roweis & Saul 2000) with out-of-sample mapping.
* :mod:`.windows`: time-delay embedding (paper 002, Eq. 9-10), recursive input update
  (Eq. 12-14), min-max scaling, chronological splits, one-step-ahead train/test pairs.
"""

from prognos_torch.datasets.ims import (
    FEATURE_NAMES,
    HI_FEATURES,
    IMS_CHANNELS,
    IMS_SAMPLES,
    PAPER_FEATURES,
    HealthIndicator,
    IMSFeatures,
    IMSFormatError,
    SkippedFile,
    bearing_channels,
    default_data_dir,
    health_indicator,
    load_ims_features,
    read_raw_features,
    read_snapshot,
    snapshot_features,
    snapshot_time,
)
from prognos_torch.datasets.lle import (
    LLEFit,
    knn,
    lle_cost_matrix,
    lle_fit,
    locally_linear_embedding,
    reconstruction_weights,
)
from prognos_torch.datasets.pronostia import (
    PRONOSTIA_AXES,
    PRONOSTIA_RECORD_SAMPLES,
    PronostiaFeatures,
    find_pronostia_bearings,
    read_pronostia_bearing,
)
from prognos_torch.datasets.windows import (
    MinMaxScaler,
    NormalizedSeries,
    OneStepPairs,
    chronological_split,
    embed,
    minmax_denormalize,
    minmax_normalize,
    one_step_pairs,
    shift_append,
)

__all__ = [
    "FEATURE_NAMES",
    "HI_FEATURES",
    "IMS_CHANNELS",
    "IMS_SAMPLES",
    "PAPER_FEATURES",
    "HealthIndicator",
    "IMSFeatures",
    "IMSFormatError",
    "SkippedFile",
    "bearing_channels",
    "default_data_dir",
    "health_indicator",
    "load_ims_features",
    "read_raw_features",
    "read_snapshot",
    "snapshot_features",
    "snapshot_time",
    "PRONOSTIA_AXES",
    "PRONOSTIA_RECORD_SAMPLES",
    "PronostiaFeatures",
    "find_pronostia_bearings",
    "read_pronostia_bearing",
    "LLEFit",
    "knn",
    "lle_cost_matrix",
    "lle_fit",
    "locally_linear_embedding",
    "reconstruction_weights",
    "MinMaxScaler",
    "NormalizedSeries",
    "minmax_normalize",
    "minmax_denormalize",
    "chronological_split",
    "embed",
    "shift_append",
    "OneStepPairs",
    "one_step_pairs",
]
