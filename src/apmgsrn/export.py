"""Models outside Python: the network as an ONNX graph, for ONNX Runtime, TensorRT, C++ or a browser.

The graph maps ``points`` ``[N, 3]`` (float32 ``(x, y, z)`` in ``[-1, 1]^3``, any ``N``) to ``values``
``[N, 1]`` in data units: the encoder, the decoder, the output scaling and the inverse value transform, as
:meth:`apmgsrn.Model.predict` computes them. It is traced from the pure-PyTorch kernels (the fused CPU and
Triton kernels are not ONNX operators). A brick model is exported evaluating every brick at every point and
keeping each point's own brick (or blending, as the model does), which the graph can express without
data-dependent shapes; it costs one network evaluation per brick and point, so a brick model of more than
:attr:`~apmgsrn.limits.Limits.export_bricks` bricks is refused (export its brick files one at a time). A graph
keeps what the model promises or is not written: a model with a voxel correction (an error bound,
``--max-error``) is refused, since the graph would compute the network alone.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from pathlib import Path

import torch
from torch import nn

from apmgsrn.limits import LIMITS
from apmgsrn.atomic import atomic_write, check_output_path, check_suffix
from apmgsrn.decomposition.bricked_field import BrickedField
from apmgsrn.errors import ApmgsrnError
from apmgsrn.models.corrected_field import CorrectedField
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import FieldConfig

#: The ONNX opset of exported graphs: 20 is the first whose GridSample samples 3-D grids (ONNX Runtime reads
#: it from release 1.17 on).
OPSET = 20


def export_onnx(field: nn.Module, path: str | os.PathLike, source: str | os.PathLike | None = None) -> Path:
    """Write a field as an ONNX graph, atomically.

    Args:
        field: a :class:`~apmgsrn.models.field.NeuralField` or a brick model
            (:class:`~apmgsrn.decomposition.bricked_field.BrickedField`).
        path: the ``.onnx`` file.
        source: the model file or folder the field came from, for messages.

    Returns:
        The path written.

    Raises:
        ApmgsrnError: the ``onnx`` package is missing; ``path`` is not a ``.onnx`` file name or is refused by
            :func:`~apmgsrn.atomic.check_output_path`; the field is of a kind that cannot be exported, holds a
            voxel correction the graph could not keep, or has more than
            :attr:`~apmgsrn.limits.Limits.export_bricks` bricks.
    """
    check_suffix(path, (".onnx",), "ONNX model")
    check_output_path(path, "ONNX model")  # before the tracing, which takes seconds per network
    try:
        import onnx  # noqa: F401 - torch's exporter needs it
    except ImportError:
        raise ApmgsrnError("exporting to ONNX needs the onnx package; run `pip install onnx`") from None
    try:
        portable = _portable(field).cpu().eval()
    except ApmgsrnError as exc:
        raise ApmgsrnError(f"{source}: {exc}" if source is not None else str(exc),
                           arguments=exc.arguments) from None
    example = torch.zeros(8, 3)

    def write(temporary: str) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the tracer's notes on Python-side constants, not problems
            torch.onnx.export(
                portable, (example,), temporary, input_names=["points"], output_names=["values"],
                dynamic_axes={"points": {0: "points"}, "values": {0: "points"}}, opset_version=OPSET,
                dynamo=False,
            )

    atomic_write(path, write, "ONNX model")
    return Path(path)


def _portable(field: nn.Module) -> nn.Module:
    """The same field computed with the pure-PyTorch kernels only, in a form the ONNX tracer can follow."""
    if isinstance(field, BrickedField):
        if len(field.bricks) > LIMITS.export_bricks:
            raise ApmgsrnError(f"a brick model of {len(field.bricks)} bricks: its ONNX graph would evaluate every "
                               f"brick at every point; export at most {LIMITS.export_bricks} bricks, e.g. each "
                               "brick file of the folder on its own")
        return EveryBrick(field, [_portable(brick) for brick in field.bricks])
    if not isinstance(field, NeuralField):
        raise ApmgsrnError(f"cannot export a {type(field).__name__}; export a model file or brick-model folder")
    if isinstance(field, CorrectedField) and field.correction_count:
        raise ApmgsrnError(f"the model keeps |model - data| <= {field.max_error:g} with a correction at "
                           f"{field.correction_count} voxels, which an ONNX graph cannot hold: its graph would "
                           "compute the network alone and break the bound; export its float32 model, or one packed "
                           "without max_error=", arguments=("max_error",))
    config = field.config
    encoder = config.encoder
    if "backend" in {f.name for f in dataclasses.fields(encoder)} and encoder.backend != "torch":
        encoder = dataclasses.replace(encoder, backend="torch")
    copy = NeuralField(FieldConfig(config.model, encoder, config.decoder), fit_min=field.fit_min,
                       fit_max=field.fit_max, value_min=field.value_min, value_max=field.value_max,
                       transform=field.transform, volume_shape=field.volume_shape)
    copy.load_state_dict(field.state_dict())
    return copy


class EveryBrick(nn.Module):
    """A brick model evaluated the traceable way: every brick at every point, weighted by each point's share.

    The weights are the routed brick's one-hot (no blending) or the blend weights of
    :meth:`~apmgsrn.decomposition.bricked_field.BrickedField.axis_weights`; the values equal the routed
    model's (a test compares them).
    """

    def __init__(self, model: BrickedField, bricks: list[nn.Module]):
        super().__init__()
        # The router lends its routing tables and weights only, not its networks: kept out of the module tree,
        # so the graph holds each brick's parameters once (the portable copies below).
        self.__dict__["model"] = model
        self.bricks = nn.ModuleList(bricks)
        counts = model.plan.counts  # bricks along x, y, z
        positions = [(i, j, k) for k in range(counts[2]) for j in range(counts[1]) for i in range(counts[0])]
        self.register_buffer("positions", torch.tensor(positions, dtype=torch.long), persistent=False)  # [B, 3]

    def weights(self, points: torch.Tensor) -> torch.Tensor:
        """``[N, B]`` share of every brick in every point's value."""
        if not self.model.blend:
            routed = self.model.route(points)  # [N, 3]
            return (routed[:, None, :] == self.positions[None, :, :]).all(-1).to(points.dtype)
        candidates, axis_weights = self.model.axis_weights(points)  # [N, 3 candidates, 3 axes] each
        # Per axis, the weight of the candidate at each brick's position along that axis (0 if none is).
        match = candidates[:, :, None, :] == self.positions[None, None, :, :]  # [N, 3, B, 3]
        per_axis = (axis_weights[:, :, None, :] * match).sum(1)  # [N, B, 3]
        return per_axis.prod(-1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        points = points.clamp(-1.0, 1.0) if self.model.blend else points
        weights = self.weights(points)  # [N, B]
        local = (points[:, None, :] * self.model.brick_scales[None] + self.model.brick_offsets[None]).clamp(-1.0, 1.0)
        values = torch.cat([brick(local[:, b]) for b, brick in enumerate(self.bricks)], dim=1)  # [N, B]
        return (values * weights).sum(1, keepdim=True)
