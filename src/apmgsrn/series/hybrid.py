"""The hybrid encoder over the steps of a series: every step its own feature tables and grid placement.

What a stepwise series of hybrid models fills (:mod:`apmgsrn.series.steps`): the start step's
hybrid model, then every other step fine-tuned from its neighbour. Every parameter of a
:class:`~apmgsrn.models.encoders.hybrid_grid.HybridGridEncoder` gains a leading step axis: ``level_table``
``[T, P]``, ``grids`` ``[T, M, R, R, R, C]``, ``matrices`` ``[T, M, 3, 3]``, ``translations`` ``[T, M, 3]``.
The layout (levels, hash, adaptive grid sizes) and the decoder are the same for every step, so one step is a
plain hybrid model (:meth:`SeriesHybridEncoder.step_state`), and consecutive steps' tables are close, which is
what the packed series file's time predictor codes.
"""

from __future__ import annotations

import torch
from torch import nn

from apmgsrn.models.encoders.adaptive_multigrid import placed_boxes
from apmgsrn.models.encoders.hybrid_grid import HybridGridConfig, HybridGridEncoder

#: Every parameter of a step (all carry the step axis).
HYBRID_STEP_PARAMETERS = ("level_table", "grids", "matrices", "translations")
#: The ones a step's fine-tune moves (its placement only when it follows moving structures).
HYBRID_STEP_FEATURES = ("level_table", "grids")


class SeriesHybridEncoder(HybridGridEncoder):
    """Encodes groups of points, each group at one step, with that step's hybrid parameters.

    Initialised as one hybrid encoder, every step a copy of it.
    """

    step_parameters = HYBRID_STEP_PARAMETERS
    step_features = HYBRID_STEP_FEATURES

    def __init__(self, config: HybridGridConfig, steps: int, generator: torch.Generator | None = None):
        super().__init__(config, generator=generator)
        self.steps = steps
        for name in HYBRID_STEP_PARAMETERS:
            single = getattr(self, name).detach()
            setattr(self, name, nn.Parameter(single.expand(steps, *single.shape).clone()))

    def step_state(self, step: int) -> dict[str, torch.Tensor]:
        """The parameters of step ``step``, named and shaped as a single hybrid encoder's."""
        return {name: getattr(self, name)[step] for name in HYBRID_STEP_PARAMETERS}

    def forward(self, points: torch.Tensor, steps: torch.Tensor, detach_placement: bool = False) -> torch.Tensor:
        """Features ``[G * n, L F + M C]`` of points ``[G * n, 3]``, group ``g`` at step ``steps[g]``."""
        groups = points.view(len(steps), -1, 3)
        return torch.cat([self.features_of(group, *self.step_state(step).values(), detach_placement)
                          for group, step in zip(groups, steps.tolist())])

    @torch.no_grad()
    def grid_boxes(self, step: int = 0) -> torch.Tensor:
        """Corners ``[M, 8, 3]`` of the adaptive grids at step ``step``."""
        return placed_boxes(self.matrices[step], self.translations[step])

    def initialize_from_volume(self, values: torch.Tensor) -> None:
        """Nothing: the steps start from their start model (:mod:`apmgsrn.series.steps`)."""
