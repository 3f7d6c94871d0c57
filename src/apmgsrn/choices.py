"""The names a user chooses from (model kinds, size presets, schedules, value transforms, ...), one list each.

The library validates against these lists and the command line offers them, so both always agree. The
module imports only the recipes (no torch, no numpy): ``apmgsrn --help`` lists the choices without loading the
library behind them.
"""

from apmgsrn.recipes import PACKING

#: Model kinds (docs/method.md §2 and §5): keys of :data:`apmgsrn.models.registry.ENCODERS`. ``apmgsrn`` is the
#: paper's (its presets and results unchanged), ``hybrid`` the default (docs/models.md).
MODEL_KINDS = ("apmgsrn", "fvsrn", "ngp", "hybrid")

#: What ``train`` and ``apmgsrn.fit`` build when no model is named (:func:`default_model`).
DEFAULT_MODEL = "hybrid"


def default_model(series: bool = False, byte_target: int | None = None, joint: bool = False) -> str:
    """The model kind to build when none is named: :data:`DEFAULT_MODEL` for a volume (or its bricks) and for a
    time series trained step by step (packed to its size by the series' own packing); the paper's ``apmgsrn``
    for a joint time series (its basis grids extend APMGSRN's). A volume's byte target (``--ratio``/``--size``,
    ``byte_target`` bytes) gets :data:`DEFAULT_MODEL` from ``PACKING.hybrid_min_bytes`` up, ``apmgsrn`` below
    (docs/packing.md)."""
    if series:
        return "apmgsrn" if joint else DEFAULT_MODEL
    if byte_target is not None and byte_target < PACKING.hybrid_min_bytes:
        return "apmgsrn"
    return DEFAULT_MODEL


#: The paper's model and its two baselines: what ``bench compress`` runs unless given ``--models`` (the
#: tables of docs/results.md); ``bench quality`` runs these and the default model.
PAPER_MODELS = ("apmgsrn", "fvsrn", "ngp")

#: Size presets of every model kind (:attr:`apmgsrn.recipes.ModelRecipe.presets`).
SIZE_PRESETS = ("small", "medium", "large")

#: How an APMGSRN model places its grids at the start. The encoder
#: (:mod:`apmgsrn.models.encoders.adaptive_multigrid`) holds the same tuple; a test keeps them equal.
GRID_INITS = ("default", "large", "small")

#: How the hybrid model places its adaptive grids at the start (:mod:`apmgsrn.models.encoders.hybrid_grid`
#: holds the same tuple; a test keeps them equal).
HYBRID_GRID_INITS = ("volume", "default")

#: Multi-grid sampling kernels (:mod:`apmgsrn.ops.multigrid`); ``"auto"`` picks the fastest usable one.
MULTIGRID_BACKENDS = ("torch", "cpu", "triton")

#: Multi-level grid sampling kernels (:mod:`apmgsrn.ops.level_grids`) of the hybrid model.
LEVEL_GRID_BACKENDS = ("torch", "cpu", "triton")

#: Kernel backends each model kind accepts. The hash grid's list is also the encoder's
#: (:mod:`apmgsrn.models.encoders.hash_grid`); a test keeps them equal.
BACKENDS = {
    "apmgsrn": ("auto", *MULTIGRID_BACKENDS),
    "fvsrn": ("auto", *MULTIGRID_BACKENDS),
    "ngp": ("torch", "tcnn", "auto"),
    "hybrid": ("auto", *LEVEL_GRID_BACKENDS),
}

#: Value transforms applied before fitting (:mod:`apmgsrn.models.value_transform`).
VALUE_TRANSFORMS = ("none", "log10", "zscore")

#: Learning-rate schedules of the trainer (:class:`apmgsrn.training.trainer.TrainConfig`).
LR_SCHEDULES = ("cosine", "constant", "plateau", "steps")

#: Normalisations of the feature density loss (:class:`apmgsrn.training.trainer.TrainConfig`).
DENSITY_NORMALIZATIONS = ("mass", "batch")

#: Precisions of the decoder's hidden layers in training (:class:`apmgsrn.training.trainer.TrainConfig`).
DECODER_PRECISIONS = ("auto", "float32", "bfloat16")

#: How the basis weights of a time-series step are set (:class:`apmgsrn.series.field.SeriesConfig`).
SERIES_COEFFICIENTS = ("learned", "keyframes", "cumulative")

#: Dtypes a time-series model stores its feature grids in: float16 halves the file for a rounding far below
#: the fit's errors.
SERIES_STORAGE = ("float32", "float16")
#: How ``train`` fits a time series (apmgsrn.series.fit).
SERIES_TRAINING = ("stepwise", "joint")

#: How a ParaView preset's node positions are read (:func:`apmgsrn.rendering.paraview.apply_preset`).
PRESET_UNITS = ("normalized", "data")

#: Lossy compressors of ``bench compress`` (:data:`apmgsrn.bench.compressors.COMPRESSORS`).
COMPRESSORS = ("sz3", "zfp", "zfp-precision", "sperr", "sperr-pwe", "tthresh")

#: Units of a decode region (:class:`apmgsrn.data.grid.Region`): voxel indices or the source's coordinates.
REGION_UNITS = ("index", "coordinates")

#: Formats of ``apmgsrn export``.
EXPORT_FORMATS = ("onnx", "html")
