"""The choices of a time-series model users type, torch-free (the command line lists them without importing
torch); :mod:`apmgsrn.series.field` builds the model."""

from apmgsrn.choices import SERIES_COEFFICIENTS as COEFFICIENT_KINDS
from apmgsrn.choices import SERIES_STORAGE as STORAGE_KINDS

#: Where a series' grids sit: one placement for every step, or one per step (what stepwise training fills).
PLACEMENT_KINDS = ("shared", "per_step")
#: Series options a user does not set (chosen by measurement, docs/time_series.md).
SERIES_DEFAULTS = {"basis": 4, "coefficients": "learned", "residual": 0, "storage": "float32"}
#: Sanity bounds of a config (a model file claiming more is refused before anything is allocated).
MAX_STEPS, MAX_BASIS = 1 << 20, 4096
