"""The choices of a time-series model users type, torch-free (the command line lists them without importing
torch); :mod:`apmgsrn.models.series_field` builds the model."""

#: How the basis weights of a step are set (see :class:`~apmgsrn.models.series_field.SeriesConfig`).
COEFFICIENT_KINDS = ("learned", "keyframes", "cumulative")
#: Dtypes the feature grids may be stored in: float16 halves the file for a rounding far below the fit's errors.
STORAGE_KINDS = ("float32", "float16")
#: Series options a user does not set (chosen by measurement, docs/time_series.md).
SERIES_DEFAULTS = {"basis": 4, "coefficients": "learned", "residual": 0, "storage": "float32"}
#: Sanity bounds of a config (a model file claiming more is refused before anything is allocated).
MAX_STEPS, MAX_BASIS = 1 << 20, 4096
