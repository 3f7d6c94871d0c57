"""Model kinds users type (``apmgsrn``, ...), their encoder classes and size presets (docs/method.md §5)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from apmgsrn.arguments import check_choice
from apmgsrn.choices import BACKENDS
from apmgsrn.errors import InvalidArgument
from apmgsrn.models.decoder import DecoderConfig
from apmgsrn.models.encoders.adaptive_multigrid import AdaptiveMultiGridConfig, AdaptiveMultiGridEncoder
from apmgsrn.models.encoders.dense_grid import DenseGridConfig, DenseGridEncoder
from apmgsrn.models.encoders.hash_grid import HashGridConfig, HashGridEncoder
from apmgsrn.models.encoders.hybrid_grid import NO_LATTICE, HybridGridConfig, HybridGridEncoder
from apmgsrn.recipes import MODELS

# model name (apmgsrn.choices.MODEL_KINDS, in that order) -> (encoder config class, encoder class)
ENCODERS: dict[str, tuple[type, type]] = {
    "apmgsrn": (AdaptiveMultiGridConfig, AdaptiveMultiGridEncoder),
    "fvsrn": (DenseGridConfig, DenseGridEncoder),
    "ngp": (HashGridConfig, HashGridEncoder),
    "hybrid": (HybridGridConfig, HybridGridEncoder),
}


def training_defaults(model: str, **given) -> dict:
    """TrainConfig fields a model kind trains with: its recipe's (:class:`~apmgsrn.recipes.ModelRecipe`), replaced
    by the ``given`` ones not None."""
    recipe = MODELS.get(model)
    defaults = {} if recipe is None else {"lr_schedule": recipe.lr_schedule, "voxel_fraction": recipe.voxel_fraction,
                                          "error_sampling": recipe.error_sampling}
    return {**defaults, **{name: value for name, value in given.items() if value is not None}}


#: Config fields that choose how to run, not what to build: never saved, so a model trained with one
#: kernel backend (say Triton on a GPU) loads anywhere and picks the fastest backend where it runs.
RUN_TIME_FIELDS = ("backend",)


@dataclass(frozen=True)
class FieldConfig:
    """Everything needed to rebuild a field's modules (saved in every model file)."""

    model: str
    encoder: object
    decoder: DecoderConfig = DecoderConfig()

    def __post_init__(self) -> None:
        if self.model not in ENCODERS:
            raise ValueError(f"unknown model kind {self.model!r}")
        # Each encoder accepts its own kernels; refused here, not at the first forward pass.
        check_choice("backend", getattr(self.encoder, "backend", "auto"), BACKENDS[self.model])

    def to_dict(self) -> dict:
        encoder = {k: v for k, v in dataclasses.asdict(self.encoder).items() if k not in RUN_TIME_FIELDS}
        return {"model": self.model, "encoder": encoder, "decoder": dataclasses.asdict(self.decoder)}

    @staticmethod
    def from_dict(data: dict) -> "FieldConfig":
        """The config a model file describes; run-time fields stored by older versions are dropped.

        Raises:
            ValueError: an unknown model kind, unknown or mistyped fields, or sizes out of bounds.
        """
        if not isinstance(data, dict) or not isinstance(data.get("model"), str):
            raise ValueError("field config is not an object with a model name")
        model = data["model"]
        if model not in ENCODERS:
            raise ValueError(f"unknown model kind {model!r}")
        config_class = ENCODERS[model][0]
        encoder = _config_fields(config_class, data.get("encoder"), "encoder")
        decoder = _config_fields(DecoderConfig, data.get("decoder"), "decoder")
        return FieldConfig(model, config_class(**encoder), DecoderConfig(**decoder))

    def fitted_to(self, volume_shape: tuple[int, int, int]) -> "FieldConfig":
        """This config for a field fitted to a ``(D, H, W)`` volume.

        An encoder whose layout follows the volume's voxel lattice (the hybrid's ``lattice``) records the
        shape here, unless it has one already (a config read from a model file); the others are unchanged.
        """
        if getattr(self.encoder, "lattice", None) != NO_LATTICE or min(volume_shape) < 1:
            return self
        return dataclasses.replace(self, encoder=dataclasses.replace(self.encoder, lattice=tuple(volume_shape)))

    def parameter_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shape of every stored parameter of the field, named as in its ``state_dict``."""
        encoder = {f"encoder.{k}": v for k, v in self.encoder.parameter_shapes().items()}
        decoder = {f"decoder.{k}": v for k, v in self.decoder.parameter_shapes(self.encoder.out_features).items()}
        return encoder | decoder

    def stored_dtypes(self) -> dict[str, torch.dtype]:
        """The dtype every parameter is stored in: what the encoder's config says (an encoder config with a
        ``stored_dtypes()``), float32 for the rest."""
        encoder = getattr(self.encoder, "stored_dtypes", dict)()
        return {name: encoder.get(name.removeprefix("encoder."), torch.float32) for name in self.parameter_shapes()}


def _hybrid_names(overrides: dict) -> dict:
    """The hybrid's adaptive grids under the names the other kinds' grids have: ``resolution`` (a cube: R or
    (R, R, R)) is its ``grid_resolution``, ``init`` its ``grid_init``."""
    overrides = dict(overrides)
    if "resolution" in overrides:
        resolution = overrides.pop("resolution")
        sizes = set(resolution) if isinstance(resolution, (tuple, list)) else {resolution}
        if len(sizes) != 1:
            raise InvalidArgument(f"resolution={resolution!r}: the hybrid's adaptive grids are cubes; give one size",
                                  arguments=("resolution",))
        overrides["grid_resolution"] = int(sizes.pop())
    if "init" in overrides:
        overrides["grid_init"] = overrides.pop("init")
    return overrides


def stored_bytes(config) -> int:
    """Bytes of the stored parameters of a field's or series field's config (every tensor in its stored
    dtype; the file adds its description)."""
    dtypes = config.stored_dtypes()
    return sum(math.prod(shape) * dtypes[name].itemsize for name, shape in config.parameter_shapes().items())


def _config_fields(config_class: type, data, name: str) -> dict:
    """Keyword arguments for ``config_class`` from stored JSON: known fields of plain types only."""
    if not isinstance(data, dict):
        raise ValueError(f"{name} config is not an object")
    known = {f.name: f for f in dataclasses.fields(config_class)}
    fields = {}
    for key, value in data.items():
        if key in RUN_TIME_FIELDS:
            continue
        if key not in known:
            raise ValueError(f"unknown {name} field {key!r}")
        default = known[key].default
        if isinstance(default, tuple):
            if not isinstance(value, (list, tuple)) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
                raise ValueError(f"{name}.{key} is not a list of integers")
            value = tuple(value)
        elif type(default) is not type(value) and not (isinstance(default, float) and type(value) is int):
            raise ValueError(f"{name}.{key} is a {type(value).__name__}, not a {type(default).__name__}")
        fields[key] = value
    return fields


def preset_config(model: str, preset: str, **overrides) -> FieldConfig:
    """A field config from a size preset, with explicit encoder/decoder fields overriding it.

    Args:
        model: model kind (a key of :data:`ENCODERS`).
        preset: ``"small"``, ``"medium"`` or ``"large"``.
        overrides: encoder config fields, plus ``hidden_layers``/``width`` for the decoder; None is ignored.
    """
    if model not in ENCODERS:
        raise ValueError(f"unknown model {model!r}; choose from {sorted(ENCODERS)}")
    presets = MODELS[model].presets
    if preset not in presets:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(presets)}")
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if model == "hybrid":
        overrides = _hybrid_names(overrides)
    decoder = DecoderConfig(
        hidden_layers=overrides.pop("hidden_layers", DecoderConfig.hidden_layers),
        width=overrides.pop("width", DecoderConfig.width),
    )
    config_class = ENCODERS[model][0]
    known = {f.name for f in dataclasses.fields(config_class)}
    for name in overrides:
        if name not in known:
            raise InvalidArgument(f"{name}={overrides[name]!r}: does not apply to {model} models",
                                  arguments=(name,))
    fields = {**presets[preset], **overrides}
    return FieldConfig(model, config_class(**fields), decoder)
