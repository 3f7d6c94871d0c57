"""Model kinds users type (``apmgsrn``, ...), their encoder classes and size presets (SPEC section 5)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from apmgsrn.models.decoder import DecoderConfig
from apmgsrn.models.encoders.adaptive_multigrid import AdaptiveMultiGridConfig, AdaptiveMultiGridEncoder
from apmgsrn.models.encoders.dense_grid import DenseGridConfig, DenseGridEncoder
from apmgsrn.models.encoders.hash_grid import HashGridConfig, HashGridEncoder
from apmgsrn.models.encoders.hybrid_grid import HybridGridConfig, HybridGridEncoder

# model name -> (encoder config class, encoder class)
ENCODERS: dict[str, tuple[type, type]] = {
    "apmgsrn": (AdaptiveMultiGridConfig, AdaptiveMultiGridEncoder),
    "fvsrn": (DenseGridConfig, DenseGridEncoder),
    "ngp": (HashGridConfig, HashGridEncoder),
    "hybrid": (HybridGridConfig, HybridGridEncoder),
}

# model name -> preset name -> encoder config fields (SPEC section 5, paper Table 1 sizes)
PRESETS: dict[str, dict[str, dict]] = {
    "apmgsrn": {
        "small": dict(grids=16, features=1, resolution=(16, 16, 16)),
        "medium": dict(grids=16, features=2, resolution=(32, 32, 32)),
        "large": dict(grids=16, features=4, resolution=(64, 64, 64)),
    },
    "fvsrn": {
        "small": dict(features=2, resolution=(32, 32, 32)),
        "medium": dict(features=4, resolution=(64, 64, 64)),
        "large": dict(features=8, resolution=(128, 128, 128)),
    },
    "ngp": {
        "small": dict(levels=17, features=2, log2_table_size=11, base_resolution=8, finest_resolution=256),
        "medium": dict(levels=18, features=2, log2_table_size=15, base_resolution=16, finest_resolution=512),
        "large": dict(levels=17, features=2, log2_table_size=20, base_resolution=16, finest_resolution=256),
    },
    # Half the features in the domain levels' tables, half in the adaptive grids; each preset holds at most
    # as many parameters as the smallest baseline of its size on any volume (tests/test_hybrid_grid.py).
    "hybrid": {
        "small": dict(levels=15, features=2, log2_table_size=10, coarsest=8, grids=8, grid_features=1,
                      grid_resolution=16),
        "medium": dict(levels=15, features=2, log2_table_size=14, coarsest=16, grids=8, grid_features=2,
                       grid_resolution=32),
        "large": dict(levels=15, features=2, log2_table_size=18, coarsest=16, grids=8, grid_features=4,
                      grid_resolution=64),
    },
}

# model name -> default learning-rate schedule of the trainer (see TrainConfig.lr_schedule). Measured under
# the CPU protocol (docs/baselines.md): the budget-following cosine also suits the baselines.
DEFAULT_LR_SCHEDULES: dict[str, str] = {"apmgsrn": "cosine", "fvsrn": "cosine", "ngp": "cosine", "hybrid": "cosine"}


@dataclass(frozen=True)
class FieldConfig:
    """Everything needed to rebuild a field's modules (saved in every model file)."""

    model: str
    encoder: object
    decoder: DecoderConfig = DecoderConfig()

    def to_dict(self) -> dict:
        return {"model": self.model, "encoder": dataclasses.asdict(self.encoder), "decoder": dataclasses.asdict(self.decoder)}

    @staticmethod
    def from_dict(data: dict) -> "FieldConfig":
        model = data["model"]
        if model not in ENCODERS:
            raise ValueError(f"unknown model kind {model!r}")
        config_class = ENCODERS[model][0]
        encoder_fields = {k: tuple(v) if isinstance(v, list) else v for k, v in data["encoder"].items()}
        return FieldConfig(model, config_class(**encoder_fields), DecoderConfig(**data["decoder"]))


def preset_config(model: str, preset: str, **overrides) -> FieldConfig:
    """A field config from a size preset, with explicit encoder/decoder fields overriding it.

    Args:
        model: model kind (a key of :data:`ENCODERS`).
        preset: ``"small"``, ``"medium"`` or ``"large"``.
        overrides: encoder config fields, plus ``hidden_layers``/``width`` for the decoder; None is ignored.
    """
    if model not in ENCODERS:
        raise ValueError(f"unknown model {model!r}; choose from {sorted(ENCODERS)}")
    if preset not in PRESETS[model]:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS[model])}")
    overrides = {k: v for k, v in overrides.items() if v is not None}
    decoder = DecoderConfig(
        hidden_layers=overrides.pop("hidden_layers", DecoderConfig.hidden_layers),
        width=overrides.pop("width", DecoderConfig.width),
    )
    config_class = ENCODERS[model][0]
    fields = {**PRESETS[model][preset], **overrides}
    return FieldConfig(model, config_class(**fields), decoder)
