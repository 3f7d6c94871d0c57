"""Recipes: every tuned number of the package, in one place.

One recipe per model kind (:class:`ModelRecipe`: its size presets, its training defaults, how its time series'
steps train) and one per kind of input or job (:data:`VOLUME`, :data:`SERIES`, :data:`PACKING`, :data:`BRICKS`,
:data:`RUNTIME`). Code reads the module-level instances; a function or config that a test or caller must run with
other numbers takes a recipe argument defaulting to them, so that ``dataclasses.replace(SERIES, share_steps=3)``
is all a small experiment needs. The figures behind the values are in docs/models.md, docs/time_series.md,
docs/results_packing.md and docs/method.md.

This module imports nothing from apmgsrn, so every layer may import it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ModelRecipe:
    """How one model kind is built and trained unless told otherwise."""

    #: encoder config fields of each size preset (small, medium, large; docs/method.md §5 and §9)
    presets: dict[str, dict[str, object]]
    #: learning-rate schedule; the budget-following cosine suits every kind under the CPU protocol (docs/baselines.md)
    lr_schedule: str = "cosine"
    #: share of a batch on voxels; +0..+8 dB at the voxels on the nine shared volumes (docs/models.md, "Voxel points")
    voxel_fraction: float = 0.0
    #: share of the voxel points drawn where the model is wrong; -0.07..+10.8 dB, mean +2.6 (docs/models.md)
    error_sampling: float = 0.0
    #: a series step's fine-tune learning rate as a share of the start model's (docs/time_series.md)
    step_lr_share: float = 0.3
    #: a series step's batch as a share of the start model's, on a CPU (docs/time_series.md)
    step_batch_share: float = 1.0
    #: a series step's points (iterations x batch) as a share of the base fine-tune's, on a CPU (docs/time_series.md)
    step_point_share: float = 1.0
    #: a series start model's iterations as a share of the configured ones, on a CPU (docs/time_series.md)
    start_iteration_share: float = 1.0
    #: pull of a series step's features towards its neighbour's, fewer bytes for a looser fit (PullTowardsStart)
    step_sparsity: float = 0.0
    #: lowest bit width of a packed series' default size target (docs/time_series.md)
    series_min_bits: int = 6
    #: a packed series' quantisation-aware fine-tune per step, as a share of the start model's iterations
    series_qat_share: float = 0.0
    #: a packed series' decoder fine-tune to the coded grids, as a share of the start model's iterations
    series_decoder_share: float = 0.0


APMGSRN = ModelRecipe(presets={
    "small": dict(grids=16, features=1, resolution=(16, 16, 16)),
    "medium": dict(grids=16, features=2, resolution=(32, 32, 32)),
    "large": dict(grids=16, features=4, resolution=(64, 64, 64)),
})
FVSRN = ModelRecipe(presets={
    "small": dict(features=2, resolution=(32, 32, 32)),
    "medium": dict(features=4, resolution=(64, 64, 64)),
    "large": dict(features=8, resolution=(128, 128, 128)),
})
NGP = ModelRecipe(presets={
    "small": dict(levels=17, features=2, log2_table_size=11, base_resolution=8, finest_resolution=256),
    "medium": dict(levels=18, features=2, log2_table_size=15, base_resolution=16, finest_resolution=512),
    "large": dict(levels=17, features=2, log2_table_size=20, base_resolution=16, finest_resolution=256),
})
# Float16 tables: each preset's stored bytes at or under the smallest baseline's of its size (docs/models.md);
# 12 domain levels, where 15 take 1.4-1.5x APMGSRN's time per iteration for 0 to 0.9 dB more.
HYBRID = ModelRecipe(
    presets={
        "small": dict(levels=12, features=2, log2_table_size=11, coarsest=8, grids=8, grid_features=1,
                      grid_resolution=21, storage="float16"),
        "medium": dict(levels=12, features=2, log2_table_size=15, coarsest=16, grids=8, grid_features=2,
                       grid_resolution=42, storage="float16"),
        "large": dict(levels=12, features=2, log2_table_size=19, coarsest=16, grids=8, grid_features=4,
                      grid_resolution=84, storage="float16"),
    },
    voxel_fraction=0.5,
    error_sampling=1.0,
    # at 0.3 the hybrid's steps end 0.2-0.9 dB below this rate (30 viscous-finger steps)
    step_lr_share=1.0,
    # 0.03-0.54 dB higher at half the batch, +0.05 dB more at 0.375 (viscous-finger steps, CPU)
    step_batch_share=0.375,
    # 0.04 dB lower than 1.0, 6 % less time: the series trains within five times one step
    step_point_share=0.9,
    # the shared decoder gains: every step of three seeds above its own model in the same time
    start_iteration_share=1.4,
    # 0.01 beats 0.02 on a series whose structures travel (0.8-1.0 dB on 9 of 10 steps)
    step_sparsity=0.01,
    # the tables cost 0.45 dB at 7 bits and 1.7 at 6; the 30 viscous-finger steps fit five files at 7
    series_min_bits=7,
    # 50 iterations after 2,000 lift every step 0.5-0.8 dB in the same bytes, 250 another 0.16-0.25
    series_qat_share=0.125,
    # 300 after 2,000: up to +0.59 dB on the steps least like the start one (docs/time_series.md)
    series_decoder_share=0.15,
)

#: model kind (:data:`apmgsrn.choices.MODEL_KINDS`) -> its recipe
MODELS: dict[str, ModelRecipe] = {"apmgsrn": APMGSRN, "fvsrn": FVSRN, "ngp": NGP, "hybrid": HYBRID}


def model_recipe(kind: str) -> ModelRecipe:
    """The recipe of model kind ``kind``.

    Raises:
        KeyError: an unknown kind.
    """
    return MODELS[kind]


@dataclass(frozen=True)
class VolumeRecipe:
    """How one volume trains by default."""

    #: iterations on a CPU: minutes on two cores
    cpu_iterations: int = 3_000
    #: points per iteration on a CPU
    cpu_batch_size: int = 32_768
    #: iterations on a GPU (the paper's)
    gpu_iterations: int = 50_000
    #: points per iteration on a GPU (the paper's)
    gpu_batch_size: int = 100_000
    #: times a run measures where it is wrong (error-guided points); every 50 iterations beats every 100 by 0.16 dB
    error_measurements: int = 20
    #: most voxels an error measurement evaluates; a larger volume is measured at one voxel per block
    error_pool: int = 1 << 18


@dataclass(frozen=True)
class SeriesRecipe:
    """How a time series trains: one model per step, warm-started from its neighbour (docs/time_series.md)."""

    #: share of a batch on voxels of a stepwise series; uniform points alone cost 2-4 dB on the viscous-finger steps
    voxel_fraction: float = 0.5
    #: adaptive grids an APMGSRN series anchors; +0.01..+1.32 dB (mean +0.62) on the 30 viscous-finger steps
    anchored_grids: int = 1
    #: a joint series model trains for at most this many times one volume's budget
    joint_budget_steps: float = 4.5
    #: a step's base fine-tune as a share of the start model's iterations; 200 after 2,000: within 0.0-0.9 dB
    step_iteration_share: float = 0.1
    #: share of the start model's voxel points drawn where it is wrong; its decoder serves every step
    start_error_sampling: float = 0.0
    #: one start-model point in fine-tune points of the steps' budget; at 2.0 the steps end 0.1-0.25 dB lower
    start_point_cost: float = 1.5
    #: a step whose change from its neighbour exceeds this many times the start model's RMS error gets more iterations
    step_change_scale: float = 8.0
    #: the most times its base share a step's fine-tune gets for its change
    step_iteration_cap: float = 10.0
    #: steps asking for less than this many times the base share it evenly (+0.16-0.22 dB on the far steps)
    step_even_below: float = 2.0
    #: the steps' fine-tunes take at most this many times the start model's points (30 steps: 4.1-4.9 steps' time)
    steps_budget_cap: float = 4.26
    #: what a step costs besides its fine-tunes, in start-model iterations (0.63 s a step on one CPU thread)
    step_fixed_cost: int = 16
    #: the least share of their base a too long series' fine-tunes are shortened to
    least_budget_scale: float = 0.05
    #: voxels compared to measure how much a step differs from its neighbour
    change_voxels: int = 1 << 20
    #: voxels a step's fine-tune is checked on against the neighbour's grids it started from
    check_voxels: int = 1 << 16
    #: a step ending more than this many dB below the start model is fine-tuned again with its placement moving
    track_db: float = 3.0
    #: the moving placement's learning rate as a multiple of the start model's placement_lr
    track_placement_lr_share: float = 2.0
    #: times a step's fine-tune measures where it is wrong
    step_error_measurements: int = 20
    #: interleaved parts of the voxels each measurement takes in turn; halves: 65.76 dB in 7.2 s, all: 65.69 in 8.3
    step_error_parts: int = 2
    #: a step's points between the voxels as a share of the start model's; +0.04-1.2 dB at the voxels
    step_off_voxel_share: float = 0.5
    #: the longest series whose default size and steps' budget do not grow with its length (the 30 viscous-finger steps)
    share_steps: int = 30
    #: a stepwise step this many dB below the start step's PSNR is reported as drifted
    drift_db: float = 6.0


@dataclass(frozen=True)
class PackingRecipe:
    """How models are packed into small files (docs/method.md §10, docs/results_packing.md, docs/time_series.md)."""

    #: stored bits per parameter at a small PSNR cost, to size a model for a byte target (4.5-7.4 at 0.1 dB)
    bits_per_parameter: float = 6.0
    #: decoders (hidden layers, width) a size target may shrink to, largest first
    decoder_ladder: tuple[tuple[int, int], ...] = ((2, 64), (2, 32), (1, 32), (1, 16))
    #: the largest share of a size target's parameters the decoder takes; an eighth costs up to 2.8 dB
    decoder_share: float = 1 / 2
    #: grids coarser than this are not worth their count: a size target halves the grids until each gets it
    min_resolution: int = 6
    #: the fewest grids a size target halves to
    min_grids: int = 4
    #: a size target's model of at most this many grids anchors one (HCCI, 10,000:1: 36.0-42.8 dB, not 27.1-30.9)
    anchor_max_grids: int = 8
    #: share of a sized hybrid's encoder parameters its domain levels take: the small preset's split (0.37), untuned
    hybrid_level_share: float = 0.375
    #: fewest rows (log2) a sized hybrid's domain level hashes into; below it the levels are fewer instead (untuned)
    hybrid_min_log2_table: int = 6
    #: a byte target's unnamed model is a hybrid from here up, APMGSRN below (hybrid -0.96 dB at 2,097 B, +7.8 at 2,614)
    hybrid_min_bytes: int = 2_400
    #: an error bound's correction quantises this much tighter than promised (float32 rounding)
    bound_margin: float = 1 / 64
    #: peak learning rate of a single field's quantisation-aware fine-tune
    qat_lr: float = 3e-3
    #: random points of a field's sensitivity estimate
    sensitivity_points: int = 1 << 18
    #: voxels compared while searching for a PSNR cost
    measure_voxels: int = 1 << 20
    #: bit width of a packed series when none is asked for: about 0.03 dB below float32
    series_bits: int = 10
    #: a stepwise series packs within this many single-step files of its preset by default
    series_models: int = 5
    #: about how many values of a hybrid's level table share a quantisation step
    level_table_group: int = 1024
    #: a sensitivity-allocated step is at most this many bits finer than the uniform one
    finest_share_bits: int = 8
    #: a single field's size search: log10 of its coarsest and finest sensitivity scale, and the lattice step
    scale_lattice: tuple[float, float, float] = (6.0, -12.0, 0.004)
    #: the lattice of bit widths a size target's search takes the finest fitting one of
    finer_resolution: float = 1 / 16
    #: share of a size target kept free for a quantisation-aware fine-tune; 250 iterations code 2.5 % larger
    tuned_bytes_margin: float = 0.03
    #: share of the decoder's float32 bytes kept free when it is fine-tuned after coding (4 bytes of 24.8 kB)
    decoder_bytes_margin: float = 0.01
    #: a series' quantisation-aware fine-tune learning rate as a share of the start model's; +0.54 dB at 0.03
    qat_lr_share: float = 0.03
    #: share of that fine-tune's voxel points drawn where the rounded step is wrong (uniform: -1.1 dB)
    qat_guided_share: float = 1.0
    #: times that fine-tune measures where it is wrong; 25 beats 5 by 0.39 dB
    qat_measurements: int = 25
    #: interleaved parts of the voxels each such measurement takes; quarters: as good in 12-17 % less time
    qat_error_parts: int = 4
    #: steps every iteration of the series' decoder fine-tune trains on
    decoder_steps_per_iteration: int = 4
    #: the decoder fine-tune's learning rate as a share of the start model's (0.1 and 0.3 within 0.1 dB)
    decoder_lr_share: float = 0.1
    #: share of the decoder fine-tune's points at voxels; 0.9 gains at the voxels and loses nothing between them
    decoder_voxel_fraction: float = 0.9


@dataclass(frozen=True)
class BricksRecipe:
    """How a volume too large for one model trains brick by brick (docs/method.md §6)."""

    #: a brick under the plateau schedule is done after this many learning-rate cuts (the paper's)
    lr_cuts: int = 3
    #: local CPU workers when none are asked for (never more than the cores)
    cpu_workers: int = 4


@dataclass(frozen=True)
class RuntimeRecipe:
    """How work is cut and run: batch, slab and memory sizes, threads."""

    #: points per forward pass of a query or decode
    query_batch: int = 2**18
    #: a time budget's probe: least seconds each phase is timed for (a second steadies the median under load)
    budget_probe_seconds: float = 1.0
    #: a time budget's probe: least and most steps timed in each phase
    budget_probe_steps: tuple[int, int] = (3, 50)
    #: voxels per decoded slab: 48 MiB of coordinates and 16 MiB of float32 values
    slab_voxels: int = 2**22
    #: voxels per z-slab when a volume's statistics are streamed (64 MiB of float32)
    stats_slab_voxels: int = 2**24
    #: rounds an idle OpenMP thread spins before it sleeps (libgomp's default 300,000); about 0.1 ms
    spin_count: int = 3000
    #: largest block glibc serves from the heap (its own ceiling on 64-bit machines)
    mmap_threshold: int = 32 << 20
    #: free memory kept at the top of the heap before any goes back to the kernel
    trim_threshold: int = 512 << 20
    #: memory the entropy coders running side by side may take together
    parallel_coding_memory: int = 2 << 30
    #: hybrid feature tables (float32 bytes) above which a CPU step sorts its batch by position
    ordered_batch_table_bytes: int = 2 * 1024 * 1024
    #: points an error measurement evaluates at once on a CPU (elsewhere 2^16): 0.09 s against 0.14 for 2^18 voxels
    cpu_measure_chunk: int = 1 << 13
    #: fewest guided draws a thread takes: below it one thread draws them (a thread's start costs about 5 us)
    draws_per_thread: int = 4096


VOLUME = VolumeRecipe()
SERIES = SeriesRecipe()
PACKING = PackingRecipe()
BRICKS = BricksRecipe()
RUNTIME = RuntimeRecipe()
