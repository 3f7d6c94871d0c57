"""Training callbacks that come with the package: the progress display."""

from __future__ import annotations

import math

from apmgsrn.progress import Progress
from apmgsrn.training.trainer import StepLosses, Trainer, TrainingCallback


class TrainingProgress(TrainingCallback):
    """Shows iteration, loss, PSNR estimate, grid state, rate and time left (see :mod:`apmgsrn.progress`); for a
    time series also the step whose running loss is highest (the one holding the series back).

    The loss is the mean of the last five recorded reconstruction losses (recorded every
    ``history_every`` iterations, so the display costs no extra device synchronisation); the PSNR
    estimate is ``-10 log10`` of it, in the ``[0, 1]`` fitted units.

    Args:
        description: label of the display.
        enabled: False shows nothing.
        fields_every: iterations between refreshes of the loss figures (they read only losses already on the
            host); the worst step's, ten times as many.
    """

    def __init__(self, description: str = "train", enabled: bool = True, fields_every: int = 10):
        self.description = description
        self.enabled = enabled
        self.fields_every = fields_every
        self._progress: Progress | None = None

    def on_start(self, trainer: Trainer) -> None:
        self._progress = Progress(trainer.config.iterations, unit="it", description=self.description,
                                  initial=trainer.state.iteration, enabled=self.enabled)

    def after_step(self, trainer: Trainer, iteration: int, losses: StepLosses) -> None:
        if iteration % self.fields_every == 0 or not self._progress.fields:
            recent = trainer.state.history["reconstruction"][-5:]
            if recent:
                mse = sum(recent) / len(recent)
                fields = dict(loss=f"{mse:.2e}", psnr=f"{-10 * math.log10(max(mse, 1e-30)):.2f}dB")
                if trainer.step_losses is not None:
                    if iteration % (10 * self.fields_every) == 0 or "worst" not in self._progress.fields:
                        fields["worst"] = _worst_step(trainer.step_losses)
                    else:
                        fields["worst"] = self._progress.fields["worst"]
                self._progress.set_fields(**fields, grids=trainer.grid_status())
        self._progress.update(1)

    def on_end(self, trainer: Trainer) -> None:
        # A run that stopped before its budget (early stop) completed too; Ctrl-C or an error did not.
        finished = trainer.state.iteration >= trainer.config.iterations or trainer.stopped_early()
        self._progress.close(completed=finished)


def _worst_step(step_losses) -> str:
    """The step of a series with the highest running loss, as ``"step 12 41.3dB"`` (one device read)."""
    losses = step_losses.nan_to_num(nan=-1.0)
    step = int(losses.argmax())
    return f"step {step} {-10 * math.log10(max(float(losses[step]), 1e-30)):.1f}dB"
