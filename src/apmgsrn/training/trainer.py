"""The training loop of SPEC section 4: two optimisers, delayed and early-stopped grid motion,
a learning rate that follows the iteration budget, atomic checkpoints and exact resume."""

from __future__ import annotations

import functools
import math
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.models.field import NeuralField
from apmgsrn.ops.trilinear import sample_volume
from apmgsrn.training.losses import feature_density_loss

LR_SCHEDULES = ("cosine", "constant", "plateau", "steps")
DENSITY_NORMALIZATIONS = ("mass", "batch")
DECODER_PRECISIONS = ("auto", "float32", "bfloat16")


@dataclass(frozen=True)
class TrainConfig:
    """How to train (SPEC section 4; defaults are the paper's unless noted).

    Attributes:
        iterations: total iterations.
        batch_size: random points per iteration.
        lr: Adam learning rate of the grids and decoder.
        transform_lr: Adam learning rate of the grid transforms.
        betas: Adam betas of both optimisers.
        density_start: iterations before the density step starts (delayed start); None: 5 % of the
            budget (paper: 500 of 50,000). Measured at 2,000 iterations, grids that move early and stop
            at half the budget leave the features time to settle: +1 to +2 dB over the paper's window.
        density_window: moving-average window of the density loss for early freezing.
        density_tolerance: relative fall below which the transforms freeze (0.01 %).
        freeze_fraction: the transforms freeze at this fraction of the budget at the latest (paper: 0.8).
        density_power: ``P`` of the flat-top Gaussian.
        density_normalization: ``"batch"`` (paper: ``rho / sum_X rho``) or ``"mass"`` (ours: share of the
            grids' total feature mass, so mass that leaves the domain counts; see
            :func:`~apmgsrn.training.losses.feature_density_loss`).
        lr_schedule: ``"cosine"`` (ours: constant while the grids move, then a half-cosine to
            ``final_lr_fraction`` over the remaining budget), ``"constant"``, or ``"plateau"`` (paper: x0.1
            when ``L_rec`` stops falling by 0.01 % over 500 iterations, after the grids froze).
            ``"steps"``: x0.33 at 40, 60 and 80 % of the budget (the NGP/fVSRN reference code).
        final_lr_fraction: learning rate at the end of the cosine schedule, relative to ``lr``.
        seed: seeds initialisation and point sampling.
        checkpoint_every: iterations between atomic training checkpoints.
        history_every: iterations between recorded loss-curve points; None: about 500 points in all.
        stop_after_lr_cuts: with ``lr_schedule="plateau"``, end training once the plateau scheduler has cut
            the learning rate this many times (paper, per brick: 3); None: run the whole budget.
        decoder_precision: dtype of the decoder's hidden matrix products in the reconstruction step
            (weights, gradients, optimiser and the output layer stay float32). ``"auto"``: bfloat16 on CPUs
            that multiply it natively (AVX512-BF16 or AMX), where it makes CPU training 20-25 % faster at the
            same PSNR (docs/benchmarks.md); float32 elsewhere. Evaluation always runs in float32.
    """

    iterations: int = 2000
    batch_size: int = 32768
    lr: float = 0.01
    transform_lr: float = 0.001
    betas: tuple[float, float] = (0.9, 0.99)
    density_start: int | None = None
    density_window: int = 1000
    density_tolerance: float = 1e-4
    freeze_fraction: float = 0.5
    density_power: int = 10
    density_normalization: str = "mass"
    lr_schedule: str = "cosine"
    final_lr_fraction: float = 0.01
    seed: int = 0
    checkpoint_every: int = 250
    history_every: int | None = None
    stop_after_lr_cuts: int | None = None
    decoder_precision: str = "auto"

    def __post_init__(self) -> None:
        object.__setattr__(self, "betas", tuple(self.betas))
        if self.history_every is None:
            object.__setattr__(self, "history_every", max(10, self.iterations // 500))
        if self.density_start is None:
            object.__setattr__(self, "density_start", max(1, round(0.05 * self.iterations)))
        if self.iterations < 1 or self.batch_size < 1:
            raise ValueError("iterations and batch size must be positive")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr schedule must be one of {LR_SCHEDULES}")
        if self.density_normalization not in DENSITY_NORMALIZATIONS:
            raise ValueError(f"density normalization must be one of {DENSITY_NORMALIZATIONS}")
        if self.decoder_precision not in DECODER_PRECISIONS:
            raise ValueError(f"decoder precision must be one of {DECODER_PRECISIONS}")


def decoder_hidden_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """The decoder's hidden-layer dtype for a :attr:`TrainConfig.decoder_precision` on ``device``."""
    if precision == "bfloat16":
        return torch.bfloat16
    if precision == "auto" and device.type == "cpu" and _cpu_has_native_bfloat16():
        return torch.bfloat16
    return None


@functools.cache
def _cpu_has_native_bfloat16() -> bool:
    """Whether this CPU has bfloat16 dot-product instructions (elsewhere oneDNN emulates them, slowly)."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            flags = next((line.split() for line in cpuinfo if line.startswith("flags")), [])
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def default_budget(device: torch.device) -> tuple[int, int]:
    """(iterations, batch size) sized for the device: minutes on a 2-core CPU, the paper's on a GPU."""
    if device.type == "cuda":
        return 50_000, 100_000
    return 3_000, 32_768


class TrainingInterrupted(Exception):
    """Raised after Ctrl-C once the checkpoint is safely written."""

    def __init__(self, iteration: int, checkpoint: Path):
        super().__init__(f"interrupted at iteration {iteration}; checkpoint saved to {checkpoint}")
        self.iteration = iteration
        self.checkpoint = checkpoint


@dataclass
class TrainingState:
    """Everything besides tensors that a resumed run needs (saved as JSON in the checkpoint)."""

    iteration: int = 0
    frozen_at: int | None = None
    elapsed: float = 0.0
    density_losses: list[float] = field(default_factory=list)  # the last two windows, for freezing
    density_steps: int = 0
    plateau_best: float = math.inf
    plateau_since: int = 0
    lr_scale: float = 1.0
    history: dict[str, list[float]] = field(
        default_factory=lambda: {"iteration": [], "reconstruction": [], "density": [], "lr": []}
    )


class Trainer:
    """Fits a :class:`NeuralField` to a volume of values already scaled to ``[0, 1]``.

    Args:
        field: the model (its ``fit_min``/``fit_max`` give the scaling to data units).
        volume: ``[D, H, W]`` fitted values scaled to ``[0, 1]``, on the training device.
        config: how to train.
        checkpoint_path: where periodic training checkpoints go (None: no checkpoints).
        fingerprint: description of the run that a resumed checkpoint must match.
        progress: show a progress bar (only when stderr is a terminal).
    """

    def __init__(
        self,
        field: NeuralField,
        volume: torch.Tensor,
        config: TrainConfig,
        checkpoint_path: Path | None = None,
        fingerprint: dict | None = None,
        progress: bool = True,
    ):
        self.field = field
        self.volume = volume
        self.config = config
        self.device = volume.device
        self.checkpoint_path = Path(checkpoint_path) if checkpoint_path else None
        self.fingerprint = fingerprint or {}
        self.progress = progress and sys.stderr.isatty()
        encoder = field.encoder
        transform_params = list(encoder.transform_parameters()) if hasattr(encoder, "transform_parameters") else []
        transform_ids = {id(p) for p in transform_params}
        network_params = [p for p in field.parameters() if id(p) not in transform_ids]
        self.network_optimizer = torch.optim.Adam(
            _learning_rate_groups(encoder, network_params), lr=config.lr, betas=config.betas
        )
        self.transform_optimizer = (
            torch.optim.Adam(transform_params, lr=config.transform_lr, betas=config.betas)
            if transform_params
            else None
        )
        self.hidden_dtype = decoder_hidden_dtype(config.decoder_precision, self.device)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.state = TrainingState()
        self._pending_density: list[torch.Tensor] = []
        if self.transform_optimizer is None:
            self.state.frozen_at = 0
        # Encoders that start from the data (hybrid: adaptive grids on the volume's detail) do it here, the
        # one place every training path (single file, bricks) goes through; a resumed run then loads its
        # checkpoint over it.
        if hasattr(encoder, "initialize_from_volume"):
            encoder.initialize_from_volume(volume)

    # ----------------------------------------------------------------------------- schedule
    def learning_rate(self, iteration: int) -> float:
        """Network learning rate at ``iteration`` (see :class:`TrainConfig`)."""
        cfg = self.config
        if cfg.lr_schedule == "constant":
            return cfg.lr
        if cfg.lr_schedule == "plateau":
            return cfg.lr * self.state.lr_scale
        if cfg.lr_schedule == "steps":
            # NGP/fVSRN reference code: x0.33 at 40, 60 and 80 % of the budget.
            cuts = sum(iteration >= int(f * cfg.iterations) for f in (0.4, 0.6, 0.8))
            return cfg.lr * 0.33**cuts
        # cosine: hold the rate while the grids may still move, then anneal over what is left.
        hold = self._freeze_deadline() if self.transform_optimizer is not None else 0
        if self.state.frozen_at is not None:
            hold = min(hold, self.state.frozen_at)
        hold = min(hold, int(cfg.iterations * 0.5))
        if iteration < hold:
            return cfg.lr
        progress = (iteration - hold) / max(cfg.iterations - hold, 1)
        floor = cfg.final_lr_fraction
        return cfg.lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress)))

    def _freeze_deadline(self) -> int:
        return int(self.config.iterations * self.config.freeze_fraction)

    # ----------------------------------------------------------------------------- one step
    def step(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One iteration: reconstruction step, then (while the grids move) the density step.

        Returns:
            (reconstruction loss, density loss or None) as detached 0-d tensors in fitted ``[0, 1]``
            units; they stay on the device so that a GPU step never waits for the host.
        """
        cfg, st = self.config, self.state
        for group in self.network_optimizer.param_groups:
            group["lr"] = self.learning_rate(st.iteration) * group.get("lr_scale", 1.0)
        points = torch.rand(cfg.batch_size, 3, generator=self.generator, device=self.device) * 2 - 1
        target = sample_volume(self.volume, points)  # [B]

        # Step 1: L_rec moves grids and decoder only (transform-detached coordinates).
        prediction = self.field.normalized(points, detach_transforms=True, hidden_dtype=self.hidden_dtype)
        prediction = prediction.view(-1)  # [B]
        error = (prediction - target).square()  # [B]
        reconstruction = error.mean()
        self.network_optimizer.zero_grad(set_to_none=True)
        reconstruction.backward()
        self.network_optimizer.step()

        # Step 2: L_density moves the transforms only, between the delayed start and the freeze.
        density_value = None
        if st.frozen_at is None and st.iteration >= cfg.density_start:
            density = self.field.encoder.feature_density(points, cfg.density_power)  # [B]
            mean_density = (
                self.field.encoder.mean_feature_density(cfg.density_power)
                if cfg.density_normalization == "mass"
                else None
            )
            density_loss = feature_density_loss(density, error.detach(), mean_density)
            self.transform_optimizer.zero_grad(set_to_none=True)
            density_loss.backward()
            self.transform_optimizer.step()
            density_value = density_loss.detach()
        return reconstruction.detach(), density_value

    def _update_freeze(self, density: torch.Tensor | None) -> None:
        """Early stop of grid motion: freeze once the windowed mean fails to fall by the tolerance.

        Density losses are gathered on the device and read back every 100 density steps (one sync).
        """
        cfg, st = self.config, self.state
        if st.frozen_at is not None:
            return
        if density is not None:
            self._pending_density.append(density)
            st.density_steps += 1
            w = cfg.density_window
            if st.density_steps % 100 == 0:
                self._flush_density()
                if len(st.density_losses) >= 2 * w:
                    recent = sum(st.density_losses[-w:]) / w
                    before = sum(st.density_losses[-2 * w : -w]) / w
                    if not recent < before * (1 - cfg.density_tolerance):
                        st.frozen_at = st.iteration + 1
        if st.iteration + 1 >= self._freeze_deadline():
            st.frozen_at = st.iteration + 1
        if st.frozen_at is not None:
            self._pending_density.clear()
            for p in self.field.encoder.transform_parameters():
                p.requires_grad_(False)

    def _flush_density(self) -> None:
        """Move device-side density losses to the state (kept to the last two windows)."""
        st = self.state
        if self._pending_density:
            st.density_losses.extend(torch.stack(self._pending_density).tolist())
            self._pending_density.clear()
        st.density_losses = st.density_losses[-2 * self.config.density_window :]

    def _update_plateau(self, reconstruction: float) -> None:
        """Paper schedule: x0.1 when ``L_rec`` has not fallen by 0.01 % for 500 iterations (grids frozen)."""
        cfg, st = self.config, self.state
        if cfg.lr_schedule != "plateau" or st.frozen_at is None:
            return
        if reconstruction < st.plateau_best * (1 - cfg.density_tolerance):
            st.plateau_best, st.plateau_since = reconstruction, st.iteration
        elif st.iteration - st.plateau_since >= 500:
            st.lr_scale *= 0.1
            st.plateau_best, st.plateau_since = reconstruction, st.iteration

    def stopped_early(self) -> bool:
        """True once the plateau scheduler made ``stop_after_lr_cuts`` cuts (each cut is x0.1)."""
        cuts = self.config.stop_after_lr_cuts
        # lr_scale is exactly 0.1 ** cuts; the half-step margin absorbs its rounding.
        return cuts is not None and self.state.lr_scale < 10.0 ** (0.5 - cuts)

    # ----------------------------------------------------------------------------- loop
    def run(self, resume: bool = False) -> TrainingState:
        """Train to ``config.iterations``; resume from the checkpoint if asked and present.

        Raises:
            TrainingInterrupted: on Ctrl-C, after saving a checkpoint.
        """
        if resume and self.checkpoint_path and self.checkpoint_path.exists():
            self.load_checkpoint(self.checkpoint_path)
        cfg, st = self.config, self.state
        self.field.train()
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(total=cfg.iterations, initial=st.iteration, unit="it", dynamic_ncols=True, leave=True)
        recent: deque[float] = deque(maxlen=5)
        start = time.perf_counter() - st.elapsed
        stop = _StopRequest() if self.checkpoint_path is not None else None
        try:
            while st.iteration < cfg.iterations and not self.stopped_early():
                if stop is not None and stop.requested:
                    # Ctrl-C lands between iterations, so the checkpoint is an exact state to resume.
                    self.save_checkpoint(self.checkpoint_path)
                    raise TrainingInterrupted(st.iteration, self.checkpoint_path)
                reconstruction, density = self.step()
                self._update_freeze(density)
                if st.iteration % cfg.history_every == 0:
                    loss = float(reconstruction)  # one host sync per recorded point
                    if not math.isfinite(loss):
                        raise ApmgsrnError(
                            f"training diverged at iteration {st.iteration} (loss {loss}); "
                            "lower --lr or check the data"
                        )
                    recent.append(loss)
                    self._update_plateau(loss)
                    st.history["iteration"].append(st.iteration)
                    st.history["reconstruction"].append(loss)
                    st.history["density"].append(float(density) if density is not None else float("nan"))
                    st.history["lr"].append(self.learning_rate(st.iteration))
                st.iteration += 1
                st.elapsed = time.perf_counter() - start
                if bar is not None:
                    bar.update(1)
                    if st.iteration % 10 == 0:
                        mse = sum(recent) / len(recent)
                        bar.set_postfix(
                            loss=f"{mse:.2e}",
                            psnr=f"{-10 * math.log10(max(mse, 1e-30)):.2f}dB",
                            grids=self.grid_status(),
                        )
                if self.checkpoint_path and st.iteration % cfg.checkpoint_every == 0 and st.iteration < cfg.iterations:
                    self.save_checkpoint(self.checkpoint_path)
        finally:
            if stop is not None:
                stop.restore()
            if bar is not None:
                bar.close()
        self.field.eval()
        return st

    def grid_status(self) -> str:
        st = self.state
        if st.frozen_at is not None:
            return f"frozen@{st.frozen_at}"
        return "moving" if st.iteration >= self.config.density_start else "waiting"

    # ----------------------------------------------------------------------------- checkpoints
    def save_checkpoint(self, path: Path) -> None:
        """Write model, optimiser moments and RNG state atomically (safetensors + JSON, no pickle)."""
        from apmgsrn.training.checkpoint import save_tensors

        self._flush_density()
        tensors = {f"model.{k}": v for k, v in self.field.state_dict().items()}
        optimizers = {"network": self.network_optimizer, "transform": self.transform_optimizer}
        groups = {}
        for name, optimizer in optimizers.items():
            if optimizer is None:
                continue
            state = optimizer.state_dict()
            groups[name] = state["param_groups"]
            for index, entry in state["state"].items():
                for key, value in entry.items():
                    tensors[f"optim.{name}.{index}.{key}"] = torch.as_tensor(value)
        tensors["generator"] = self.generator.get_state()
        description = {
            "fingerprint": self.fingerprint,
            "config": asdict(self.config),
            "state": asdict(self.state),
            "param_groups": groups,
        }
        save_tensors(path, tensors, "training-state", description)

    def load_checkpoint(self, path: Path) -> None:
        """Restore a checkpoint written by :meth:`save_checkpoint` for the same run."""
        from apmgsrn.training.checkpoint import load_tensors, read_header

        header = read_header(path)
        if header["kind"] != "training-state":
            raise ApmgsrnError(f"{path}: not a training checkpoint; remove it or pass another --out")
        description = header["description"]
        if description.get("fingerprint") != _jsonable(self.fingerprint) or description.get("config") != _jsonable(
            asdict(self.config)
        ):
            raise ApmgsrnError(
                f"{path}: checkpoint was made with other data or settings; rerun with the same options, "
                "or delete it to start over"
            )
        tensors = load_tensors(path)
        self.field.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
        optimizers = {"network": self.network_optimizer, "transform": self.transform_optimizer}
        for name, optimizer in optimizers.items():
            if optimizer is None:
                continue
            state: dict = {}
            prefix = f"optim.{name}."
            for key, value in tensors.items():
                if key.startswith(prefix):
                    index, entry = key[len(prefix) :].split(".", 1)
                    state.setdefault(int(index), {})[entry] = value.to(self.device) if entry != "step" else value
            optimizer.load_state_dict({"state": state, "param_groups": description["param_groups"][name]})
        self.generator.set_state(tensors["generator"])
        self.state = TrainingState(**description["state"])
        if self.state.frozen_at is not None:
            for p in self.field.encoder.transform_parameters():
                p.requires_grad_(False)


def _learning_rate_groups(encoder, parameters: list) -> list:
    """Optimiser parameter groups: one per learning-rate multiplier the encoder asks for
    (``learning_rate_scales()``, per-component learning rates; the group's ``lr_scale``), or the plain
    parameter list when it asks for none."""
    scales_of = encoder.learning_rate_scales() if hasattr(encoder, "learning_rate_scales") else {}
    if not scales_of:
        return parameters
    groups: dict[float, list] = {}
    for p in parameters:
        groups.setdefault(float(scales_of.get(p, 1.0)), []).append(p)
    return [{"params": params, "lr_scale": scale} for scale, params in groups.items()]


class _StopRequest:
    """Turns Ctrl-C (SIGINT) into a flag the loop reads between iterations (main thread only)."""

    def __init__(self) -> None:
        import signal
        import threading

        self.requested = False
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)

    def _handle(self, signum, frame) -> None:
        self.requested = True

    def restore(self) -> None:
        import signal

        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def _jsonable(value):
    """The value as it reads back from JSON (tuples become lists)."""
    import json

    return json.loads(json.dumps(value))
