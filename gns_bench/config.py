"""Typed configuration: every ablation axis of the paper is a field here, with the paper's default.

A config is loaded from TOML (sections `[model]`, `[train]`, `[eval]`), then `key=value` overrides
with dotted keys (`model.message_passing_steps=5`) are applied, then it is validated once. Errors name
the file and the key. The resolved config is logged whole (`Config.flat()`), so no default hides deep
in the call chain.
"""

from __future__ import annotations

import dataclasses
import functools
import tomllib
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

# The budgets a sweep, a dataset and a report come in (sweeps/tiers.toml; datasets/<domain>.toml [tiers.*]),
# from the cheapest: smoke (a pipeline check), small (the first CPU protocol), cpu (the CPU campaign's, chosen
# by sweeps/studies/cpu_budget.toml), paper (the paper's budget, for GPUs).
TIERS = ("smoke", "small", "cpu", "paper")


class ConfigError(ValueError):
    """A bad configuration value; the message names the source and the key."""


@dataclass
class ModelConfig:
    """The learned simulator (paper Sec. 3-4.2, App. A; DeepMind's release, learning_to_simulate/)."""

    # The learned simulator: the paper's GNS, one of the baselines it is compared with (Sec. 5.5, App. D), each
    # with its own section ([cconv], [dpi]) for what it does differently, or a registered model of one's own
    # (gns_bench/simulators.py: a registered name, an entry point's, or "package.module:SPEC").
    architecture: str = "gns"
    message_passing_steps: int = 10  # M
    latent_size: int = 128
    mlp_hidden_layers: int = 2
    mlp_hidden_size: int = 128
    shared_processor: bool = False  # the paper's default is unshared GN blocks
    position_encoding: Literal["relative", "absolute"] = "relative"
    # What a node sums over its incoming edges (network.py): the edge MLP's outputs, as graph_nets'
    # InteractionNetwork in the release does, or the residual-updated edges e + phi_e (gns-bench before it
    # followed the release).
    aggregate: Literal["messages", "updated_edges"] = "messages"
    # Initial weights: Sonnet 1.x's, as the release built its MLPs (truncated normal of std 1/sqrt(fan_in),
    # zero biases; the type embedding Glorot-uniform, tf.get_variable's default), or PyTorch's defaults.
    init: Literal["sonnet", "torch"] = "sonnet"
    self_edges: bool = True  # the release's radius graph keeps i -> i (connectivity_utils, add_self_edges)
    # The release embeds the particle type for every dataset (train.py fixes 9 types, so its
    # `num_particle_types > 1` test always holds); "multiple_types" skips it for single-type datasets.
    type_embedding: Literal["always", "multiple_types"] = "always"
    # The release gives every particle its clipped distances to the bounds (App. B.2); "walls_only" gives
    # them only where the dataset's metadata says the bounds are walls (FLUIDSHAKE's container moves).
    wall_features: Literal["always", "walls_only"] = "always"
    # How far the wall distances reach, in multiples of R: d / R clipped to [-wall_range, wall_range]. The
    # release's 1 suffices where a solver's wall acts within R of the bound; an MPM grid's wall nodes act on a
    # particle 1.5 cells away (the quadratic B-spline's reach), about 2 R above the bound at grid 64, where a
    # clip at R hides the floor from material that stops before it reaches R (reports/NOTES.md, the floor out
    # of sight). CConv's wall distances (`cconv.wall_features`) reach as far.
    wall_range: float = 1.0
    global_latent: bool = False  # a global latent updated per GN block (ablation, App. C.1)
    gravity_bias: bool = False  # add the dataset's known gravity to the decoder output (ablation)
    linear_encoder_decoder: bool = False  # linear instead of MLP encoder/decoder (ablation)
    particle_type_embedding_size: int = 16
    input_sequence_length: int = 6  # positions in the input window: C = 5 velocities
    # R; None: the dataset's default_connectivity_radius, filled in by `resolve_for_dataset` where the
    # dataset is opened, so runs log and checkpoint the number
    connectivity_radius: float | None = None
    neighbour_backend: Literal["scipy", "torch_cluster", "cell_list"] = "scipy"

    def validate(self) -> None:
        # Whether the name is registered is checked where a run starts (pipeline.train_run, simulators.get):
        # the registry sits above the config, which imports nothing of gns_bench's.
        _require(bool(self.architecture.strip()), "model.architecture", "must name a simulator")
        _require(self.message_passing_steps >= 0, "model.message_passing_steps", "must be >= 0")
        _require(self.latent_size > 0, "model.latent_size", "must be > 0")
        _require(self.wall_range > 0, "model.wall_range", "must be > 0 (multiples of R)")
        _require(self.mlp_hidden_layers >= 0, "model.mlp_hidden_layers", "must be >= 0")
        _require(self.mlp_hidden_size > 0, "model.mlp_hidden_size", "must be > 0")
        _require(self.input_sequence_length >= 2, "model.input_sequence_length",
                 "must be >= 2 (one velocity needs two positions)")
        _require(self.connectivity_radius is None or self.connectivity_radius > 0,
                 "model.connectivity_radius", "must be > 0")
        _require(self.particle_type_embedding_size > 0, "model.particle_type_embedding_size", "must be > 0")


@dataclass
class TrainConfig:
    """One-step training with random-walk noise (paper Sec. 4.3, App. B.3)."""

    steps: int = 20_000_000
    batch_size: int = 2  # graphs per batch
    learning_rate: float = 1e-4
    learning_rate_final: float = 1e-6
    learning_rate_decay_steps: float = 5e6  # lr = (lr0 - lr_final) * 0.1^(step / decay) + lr_final
    noise_std: float = 3e-4  # sigma_v: the paper's GOOP optimum; the released code used 6.7e-4
    position_correction: float = 0.0  # 0 = correct velocity noise (paper default) .. 1 = position noise
    # Training windows: uniform over every window of every trajectory (the release), or with this share of each
    # batch drawn from the first `start_windows` windows of a trajectory, where rollouts start and blocks are
    # in the air nearly at rest (data/windows.py `WindowSampler` says why that matters).
    # Linear warm-up of the learning rate over the first steps (0: none, as the paper; LagrangeBench warms up).
    learning_rate_warmup_steps: int = 0
    # A linear anneal over the last steps of the run (0: none, as the paper), from the rate the schedule has
    # where it begins down to `learning_rate_anneal_to` at step `steps`. With the decay turned off
    # (`learning_rate_final = learning_rate`) this is the warm-up, stable, decay schedule (Hägele et al. 2024):
    # a budget trained at the peak rate, then annealed, where the exponential decay compressed into a short run
    # spends its rate before the model has learned what it must (reports/study-peer).
    learning_rate_anneal_steps: int = 0
    learning_rate_anneal_to: float = 1e-6  # the rate the anneal ends at
    # Pushforward (Brandstetter et al. 2022, as LagrangeBench trains): from step `pushforward_start`, a share
    # `pushforward_share` of the steps first rolls the model forward 1..`pushforward_steps` steps (drawn
    # uniformly) without gradient from the noisy window, then trains the next step from the window its own
    # predictions made, its target corrected for the drift as `position_correction` corrects for the input noise
    # (the default: the true next velocity from where the rollout stands; `train/losses.pushed_forward`). 0 steps:
    # off.
    pushforward_steps: int = 0
    pushforward_start: int = 0
    pushforward_share: float = 0.5
    start_window_share: float = 0.0
    start_windows: int = 50
    # Held-still windows (not in the paper: 0 is its training): this share of each batch replaced by a frame
    # where every moving particle is in free fall, held at rest and let go, the window ending 0 to 5 steps after
    # the release, its target the fall from rest at g. A rollout that stops a block in mid-air reaches that
    # state, which the paper's windows never show (`data/free_fall.py`; the `held_gravity_ratio` diagnostic
    # measures it). Needs the dataset's g.
    held_share: float = 0.0
    # An exponential moving average of the weights (not in the paper: 0 is its training, the last weights): the
    # average moves 1 - weight_average of the way to the weights after each step (train/averaging.py), and the
    # run's evaluations, curve points and checkpointed model for testing use it. 0.999 averages over about the
    # last 1,000 steps. At the constant rate of a learning curve a snapshot's gravity ratio swung between -0.10
    # and 1.27 from one point to the next on WATER (reports/study-gravity_curve_water).
    weight_average: float = 0.0
    seed: int = 0
    checkpoint_every: int = 1000
    # Keep the checkpoint of every curve point (`eval_every`) as checkpoint-<step>.pt beside checkpoint.pt, and
    # start a run from one of them (`init_from`: its weights, optimiser state, step and training time; the run
    # may differ from the one that wrote it only in `steps`, the anneal and what a resume may change). A run
    # trained at a constant rate is then annealed from any point of its curve for a few steps (a branch), and
    # each branch's error is what that budget buys with a schedule fitted to it. In a sweep, `init_from` may
    # name "runs:<sweep>/<tier>/<run>/checkpoint-<step>.pt" under the runs root, `{seed}` the run's seed.
    keep_checkpoints: bool = False
    init_from: str = ""
    log_every: int = 100
    device: str = "auto"  # "auto" picks CUDA when present
    # torch CPU threads; None: every usable core. "auto": the count that trains fastest here, measured by a short
    # probe (gns_bench/autotune.py): on an AVX2-only AMD EPYC two threads made a step slower than one in one session
    # and faster in the next.
    num_threads: int | Literal["auto"] | None = None
    # bf16: autocast the network (features and loss stay fp32). "auto": whichever trains fastest on this
    # machine, measured by a short probe (gns_bench/autotune.py); the run records what it used.
    precision: Literal["fp32", "bf16", "auto"] = "fp32"
    # torch.compile the network (dynamic shapes: one compilation serves every graph size, ~1 min at start).
    # It paid in bf16 on an Intel Xeon with AMX and cost on an AMD EPYC; "auto" measures it on the machine.
    compile: bool | Literal["auto"] = False
    # How the C library's allocator treats the memory a step frees. "keep": glibc's malloc keeps it mapped
    # (devices.keep_memory_mapped: 1.9x faster fp32 training on an Intel Xeon, where the default hands large
    # blocks back to the kernel every step); "system": the library's defaults, or GLIBC_TUNABLES as set.
    # "auto": keep, unless GLIBC_TUNABLES is set (the user chose). The run records what it used.
    allocator: Literal["auto", "keep", "system"] = "auto"
    # Kinematic particles are not in the loss: skip their decoder, last node update and the last block's messages
    # into them (as rollouts do, eval.moving_only). The same loss and gradients up to float rounding.
    moving_only: bool = True
    # Stop at the first step after this much training time (seconds, over resumes; periodic evaluation not
    # counted). For budget studies, whose runs get equal time; tiers define runs by steps, so results do not
    # depend on the machine's speed.
    max_wall_seconds: float | None = None
    # Every this many steps (0: never), roll the model out on the first `eval_trajectories` validation
    # trajectories for `eval_rollout_steps` steps and log `curve/...` metrics at that step with the training
    # time so far: error against wall time, without touching the test split.
    eval_every: int = 0
    eval_trajectories: int = 2
    eval_rollout_steps: int = 100

    def validate(self) -> None:
        _require(self.steps >= 0, "train.steps", "must be >= 0")
        _require(self.batch_size >= 1, "train.batch_size", "must be >= 1")
        _require(self.learning_rate > 0, "train.learning_rate", "must be > 0")
        _require(0 <= self.learning_rate_final <= self.learning_rate, "train.learning_rate_final",
                 "must be in [0, learning_rate]")
        _require(self.learning_rate_decay_steps > 0, "train.learning_rate_decay_steps", "must be > 0")
        _require(self.noise_std >= 0, "train.noise_std", "must be >= 0")
        _require(0.0 <= self.position_correction <= 1.0, "train.position_correction", "must be in [0, 1]")
        _require(0.0 <= self.start_window_share <= 1.0, "train.start_window_share", "must be in [0, 1]")
        _require(self.start_windows >= 1, "train.start_windows", "must be >= 1")
        _require(0.0 <= self.held_share <= 1.0, "train.held_share", "must be in [0, 1]")
        _require(0.0 <= self.weight_average < 1.0, "train.weight_average", "must be in [0, 1) (0 turns it off)")
        _require(self.checkpoint_every >= 1, "train.checkpoint_every", "must be >= 1")
        _require(self.log_every >= 1, "train.log_every", "must be >= 1")
        _require(self.num_threads in (None, "auto") or (isinstance(self.num_threads, int) and self.num_threads >= 1),
                 "train.num_threads", "must be >= 1, or \"auto\"")
        _require(self.max_wall_seconds is None or self.max_wall_seconds > 0, "train.max_wall_seconds", "must be > 0")
        _require(self.learning_rate_warmup_steps >= 0, "train.learning_rate_warmup_steps", "must be >= 0")
        _require(0 <= self.learning_rate_anneal_steps <= self.steps, "train.learning_rate_anneal_steps",
                 f"must be within [0, train.steps = {self.steps}]")
        _require(not self.learning_rate_anneal_steps or 0 <= self.learning_rate_anneal_to <= self.learning_rate,
                 "train.learning_rate_anneal_to", "must be within [0, learning_rate]")
        _require(self.pushforward_steps >= 0, "train.pushforward_steps", "must be >= 0 (0 turns it off)")
        _require(self.pushforward_start >= 0, "train.pushforward_start", "must be >= 0")
        _require(0.0 <= self.pushforward_share <= 1.0, "train.pushforward_share", "must be within [0, 1]")
        _require(self.eval_every >= 0, "train.eval_every", "must be >= 0 (0 turns it off)")
        _require(self.eval_trajectories >= 1, "train.eval_trajectories", "must be >= 1")
        _require(self.eval_rollout_steps >= 1, "train.eval_rollout_steps", "must be >= 1")


@dataclass
class CConvConfig:
    """Every choice of the CConv baseline; defaults are the authors' (file: line in DeepLagrangianFluids)."""

    layer_channels: list[int] = field(default_factory=lambda: [32, 64, 64])  # default_torch.py:22, then D outputs
    filter_resolution: int = 4  # K: a 4x4x4 filter (default_torch.py:11), 4x4 in 2D
    coordinate_mapping: Literal["ball_to_cube_volume_preserving", "ball_to_cube_radial"] = (
        "ball_to_cube_volume_preserving")  # default_torch.py:13
    window: Literal["poly6", "none"] = "poly6"  # default_torch.py:15, 37-38
    normalize: bool = False  # default_torch.py:52
    # The convolution radius; None: the dataset's connectivity radius R, filled in by CConvSimulator. The authors'
    # radius is half the filter extent 1.5 * 6 particle radii (default_torch.py:29), i.e. 2.25 particle spacings;
    # our R is ~1.5 spacings (datasets/*.toml), so 1.5 * R would match theirs. R is the default: CConv then sees
    # the same neighbourhood as GNS's graph, and the edges are those the pipeline already searches.
    radius: float | None = None
    # The authors' network runs in SI units on their data (particle radius 0.025 m, frames 1/50 s): velocities of
    # order 1 m/s enter as features and the 1/128 output scale suits corrections in metres. Ours runs in those
    # units too: lengths scaled so the convolution radius is theirs (0.5 * 1.5 * 6 * 0.025 m), time so a stored
    # frame lasts their 1/50 s (default_torch.py:16). reference_radius = radius and reference_dt = 1 give raw units.
    reference_radius: float = 0.1125
    reference_dt: float = 1 / 50
    correction_scale: float = 1 / 128  # default_torch.py:159
    # "euler": v* = v + g, x* = x + v* (dt = 1), exact for our finite-difference velocities under gravity alone.
    # "trapezoid": x* = x + (v + v*) / 2, the authors' code (default_torch.py:96-97), exact for their data's
    # instantaneous velocities; on finite differences it lags free fall by g / 2, which the network must learn.
    integrator: Literal["euler", "trapezoid"] = "euler"
    gravity: list[float] | None = None  # per stored frame squared; None: metadata.gravity
    # Fluid particles also get GNS's clipped wall distances (App. B.2, to `model.wall_range` R) through the
    # authors' `other_feats` input: most of our datasets have walls at the bounds and no wall particles, which
    # CConv alone would not see.
    # None: where metadata.walls says the bounds are walls.
    wall_features: bool | None = None
    neighbour_backend: Literal["scipy", "torch_cluster", "cell_list"] = "scipy"
    # Loss (train_network_torch.py:111-119, 134-145): 128 * mean over steps of the mean over fluid particles of
    # exp(-n_i / 40) * (|x_pred - x_true|^2 + 1e-9)^(gamma / 2), distances in the reference units.
    gamma: float = 0.5
    neighbour_scale: float = 1 / 40
    distance_epsilon: float = 1e-9
    loss_scale: float = 128.0
    unrolled_steps: int = 2  # window=3 (train_network_torch.py:57): two predicted steps, weighted 0.5 each
    # Training (train_network_torch.py:19, 67-95; dataset_reader_physics.py:50-55): Adam(lr 1e-3, eps 1e-6),
    # 16 scenes a batch, 50k iterations, lr factors piecewise constant after the boundaries; random rotations
    # about the gravity axis as augmentation (the training loop's job).
    # Their batch is 16 scenes and their run 50k steps: `train.batch_size` and `train.steps` here. Their schedule
    # is CConv's own (the loop asks the architecture for it); its boundaries are fractions of the run, so the
    # 25k/30k/.../45k of their 50k steps compress into any budget as the GNS schedule does. Their augmentation,
    # random rotations about the gravity axis, is not done here (a 2D scene has no rotation that keeps gravity).
    learning_rate: float = 1e-3
    adam_eps: float = 1e-6
    lr_boundaries: list[float] = field(default_factory=lambda: [0.5, 0.6, 0.7, 0.8, 0.9])
    lr_factors: list[float] = field(default_factory=lambda: [1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125])

    def validate(self) -> None:
        def require(condition: bool, key: str, message: str) -> None:
            if not condition:
                raise ConfigError(f"cconv.{key}: {message}")

        require(len(self.layer_channels) >= 1 and all(c > 0 for c in self.layer_channels), "layer_channels",
                "at least one positive width")
        require(self.filter_resolution >= 2, "filter_resolution", "must be >= 2")
        require(self.radius is None or self.radius > 0, "radius", "must be > 0")
        require(self.reference_radius > 0 and self.reference_dt > 0, "reference_radius", "units must be > 0")
        require(self.unrolled_steps >= 1, "unrolled_steps", "must be >= 1")
        require(len(self.lr_factors) == len(self.lr_boundaries) + 1, "lr_factors", "one more than lr_boundaries")
        require(all(0 < b < 1 for b in self.lr_boundaries), "lr_boundaries", "fractions of the run, in (0, 1)")


@dataclass
class DPIConfig:
    """Every choice of the model, with the authors' BoxBath values (train.py) unless said otherwise."""

    # The leaf-to-leaf radius as a multiple of the dataset's connectivity radius. Theirs is 0.08 in FleX
    # units, 1.45 water spacings (restDistance 0.055: PyFleX bindings/scenes/yz_boxbath.h); our R is 1.5
    # spacings (datasets/boxbath.toml), so 1.0 keeps their radius, counted in spacings, within 3%.
    radius_scale: float = 1.0
    pstep: int = 2  # propagation steps of the leaf-to-leaf stage
    root_pstep: int = 2  # of the root-to-root stage (their phases_dict["root_pstep"] = [[args.pstep]])
    roots_per_rigid_body: int = 8  # their root_num [[8]]: k-means clusters of the cube, one root each
    n_his: int = 0  # past velocities beyond the current one in the state (BoxBath: 0)
    nf_relation: int = 300
    nf_particle: int = 200
    nf_effect: int = 200
    # "transform": theirs, one rigid motion per body from the mean effect of its particles; "velocity":
    # rigid particles get the particle head's velocities and only the projection makes them rigid.
    rigid_head: Literal["transform", "velocity"] = "transform"
    project_rigid: bool = True  # ours: rigid_projection of every prediction onto the rest shape
    neighbour_backend: Literal["scipy", "torch_cluster", "cell_list"] = "scipy"
    self_edges: bool = True  # their ball query returns each fluid particle as its own neighbour
    # Their training is set with `train.*` (one training loop): Adam at 1e-4 (the default), batch 1 with the
    # gradients of 2 samples averaged (`train.batch_size = 2` averages the same two), no input noise
    # (`train.noise_std = 0`). Their ReduceLROnPlateau on the validation loss is not done here: the decay is
    # the GNS's exponential one. The window length is `model.input_sequence_length` (DPI reads its last
    # n_his + 2 frames and rollouts start where the GNS's do).

    def validate(self) -> None:
        for key in ("pstep", "root_pstep", "roots_per_rigid_body", "nf_relation", "nf_particle", "nf_effect"):
            _require(getattr(self, key) >= 1, f"dpi.{key}", "must be a positive integer")
        _require(self.n_his >= 0, "dpi.n_his", "must be >= 0")
        _require(self.radius_scale > 0, "dpi.radius_scale", "must be > 0")


MonitorName = Literal["non_finite", "out_of_bounds", "energy_blowup", "density_collapse"]
MONITORS: tuple[MonitorName, ...] = typing.get_args(MonitorName)
# What an evaluation computes (`eval.metrics`): the one-step MSEs (paper Sec. 4.4); rollouts with their MSEs,
# the constant-velocity baseline, the MSE at fixed horizons and the registered metrics of one's own; the
# distributional metrics (App. B.4) and the kinetic-energy error; the physical diagnostics (gravity ratio, wall
# passes, centre of mass). The last two score rollouts, so they come with "rollout".
MetricGroup = Literal["one_step", "rollout", "distribution", "diagnostics"]
METRIC_GROUPS: tuple[MetricGroup, ...] = typing.get_args(MetricGroup)


@dataclass
class EvalConfig:
    """Evaluation (paper Sec. 4.4): one-step and rollout MSE on a held-out split."""

    split: Literal["valid", "test"] = "test"
    max_trajectories: int | None = None  # None: every trajectory of the split
    rollout_steps: int | None = None  # None: to the end of each trajectory
    # Only these are computed (METRIC_GROUPS); without "rollout" nothing is rolled out (a one-step-only curve).
    metrics: list[MetricGroup] = field(default_factory=lambda: list(METRIC_GROUPS))
    one_step_windows: int | None = None  # windows per trajectory for one-step MSE; None: all
    # Distributional metrics (paper App. B.4): MMD and optimal transport between the predicted and true
    # clouds of moving particles, at `distribution_steps` evenly spaced rollout steps (the last included).
    distribution_steps: int = 10
    # Larger clouds: a fixed uniform subsample (same particles). OT is exact EMD at every size (App. B.4 /
    # C.3): 1.4-8 s a call at 8000 particles on a 2-core CPU, ~2.5 GB peak (dense N x N matrices).
    distribution_max_particles: int | None = 8000
    mmd_bandwidth_radii: float = 2.0  # Gaussian kernel width h = this x connectivity radius R
    # Rollouts: health monitors (always on unless switched off), Verlet lists, reduced precision.
    # Watch for NaN/inf, escape from the bounds, energy blow-up, density collapse: true (all four), false
    # (none), or a list of the ones to run (MONITORS); only those run, and `stop_on` applies among them.
    monitors: bool | list[MonitorName] = True
    # The monitors that end a rollout; the others only flag it (tag `<split>/rollouts_flagged`) and it runs on.
    # The paper scores whole rollouts, so a particle through a wall is error its MSE counts. NaN and runaway
    # energy leave nothing worth scoring, and a collapsed patch crowds every particle's neighbourhood: GOOP
    # test rollouts run on past one averaged 0.73-1.43 s a step, against 0.12-0.18 s without (small tier).
    stop_on: list[MonitorName] = field(default_factory=lambda: ["non_finite", "energy_blowup",
                                                                "density_collapse"])
    # Verlet neighbour lists (model/neighbours.py `VerletNeighbours`): the same edges in the same order, fewer
    # searches. > 0: this skin; 0: a fresh search every step; "auto": a probe on the first trajectory's true
    # frames times each candidate skin against none and keeps the fastest (`autotune.choose_neighbour_skin`;
    # the run's tag `<split>/neighbour_skin` says what it chose and why).
    neighbour_skin: float | Literal["auto"] = "auto"
    # Rollouts skip what kinematic particles would cost beyond their encoding and their messages out (their
    # positions come from the data): the decoder, the last node update, the last block's messages into them.
    moving_only: bool = True
    # The encoder's latents of never-moving particles and of the edges among them, computed at a rollout's
    # first step and reused (model/static_encodings.py): the same up to the rounding of smaller products.
    static_encodings: bool = True
    precision: Literal["fp32", "bf16", "fp64"] = "fp32"  # bf16: autocast the network; fp64: a reference
    # torch.compile the network for rollouts, its weights frozen as constants (model/precision.py
    # `compiled_for_inference`): about 15 s of compiling a process; the same function up to float rounding.
    # A gain in bf16 (WATERDROP rollout step 43 -> 31 ms on a 2-core AMD EPYC, reports/bench), not in fp32
    # (118 -> 139 ms in that run). "auto": a short probe here decides (evaluate.py `rollout_model`; the run's
    # tag `<split>/rollout_compile` says what it chose). Not with fp64. (The rollout's precision has no "auto":
    # it changes the errors a report shows, so a tier fixes it.)
    compile: bool | Literal["auto"] = False

    def validate(self) -> None:
        _require(self.compile in (True, False, "auto"), "eval.compile", "must be true, false or \"auto\"")
        _require(not (self.compile and self.precision == "fp64"), "eval.compile",
                 "must be false with eval.precision = fp64 (the fp64 reference runs eagerly)")
        _require(self.max_trajectories is None or self.max_trajectories >= 1, "eval.max_trajectories",
                 "must be >= 1")
        _require(self.rollout_steps is None or self.rollout_steps >= 1, "eval.rollout_steps", "must be >= 1")
        _require(self.one_step_windows is None or self.one_step_windows >= 1, "eval.one_step_windows",
                 "must be >= 1")
        _require(self.distribution_steps >= 0, "eval.distribution_steps", "must be >= 0 (0 turns them off)")
        _require(self.distribution_max_particles is None or self.distribution_max_particles >= 2,
                 "eval.distribution_max_particles", "must be >= 2")
        _require(self.mmd_bandwidth_radii > 0, "eval.mmd_bandwidth_radii", "must be > 0")
        _require(self.neighbour_skin == "auto" or self.neighbour_skin >= 0, "eval.neighbour_skin",
                 "must be >= 0 or \"auto\"")
        _require(bool(self.metrics) and all(m in METRIC_GROUPS for m in self.metrics), "eval.metrics",
                 f"must name at least one of {list(METRIC_GROUPS)}, got {self.metrics!r}")
        _require("rollout" in self.metrics or not {"distribution", "diagnostics"} & set(self.metrics),
                 "eval.metrics", "\"distribution\" and \"diagnostics\" score rollouts: list \"rollout\" with them")
        _require(isinstance(self.monitors, bool) or all(m in MONITORS for m in self.monitors), "eval.monitors",
                 f"must be true, false or a list of {list(MONITORS)}, got {self.monitors!r}")


STRESS_TESTS = ("horizon", "precision", "perturbation", "scale")


@dataclass
class StressConfig:
    """Stress tests and generalisation rollouts of a trained model (gns_bench/stress): nothing runs unless
    `tests` or `generalisation` name something. Scenes come from dataset variants (`datasets/variants/`):
    `<domain>-long` (horizon), `<domain>-jitter` (the solver's own sensitivity), `<domain>-x<s>` (scale)."""

    tests: list[str] = field(default_factory=list)  # any of STRESS_TESTS
    generalisation: list[str] = field(default_factory=list)  # variant ids to evaluate on, e.g. "continuous-heldout"
    dataset_tier: str = ""  # tier of the variant datasets ("": the training data's tier)
    max_trajectories: int = 2  # per test and per generalisation dataset
    rollout_steps: int | None = None  # cap on every stress rollout (None: the scene's whole length)
    precisions: list[str] = field(default_factory=lambda: ["fp64", "fp32", "bf16"])
    perturbation_std: float = 0.0  # initial position noise; 0: the jitter variant's `initial_jitter`
    scales: list[int] = field(default_factory=lambda: [2, 8, 34])

    def validate(self) -> None:
        for name in self.tests:
            _require(name in STRESS_TESTS, "stress.tests", f"unknown test {name!r}; expected some of {STRESS_TESTS}")
        for p in self.precisions:
            _require(p in ("fp64", "fp32", "bf16"), "stress.precisions", f"unknown precision {p!r}")
        _require(self.dataset_tier in ("", *TIERS), "stress.dataset_tier", f"expected one of {TIERS} or empty")
        _require(self.max_trajectories >= 1, "stress.max_trajectories", "must be >= 1")
        _require(self.rollout_steps is None or self.rollout_steps >= 1, "stress.rollout_steps", "must be >= 1")
        _require(self.perturbation_std >= 0, "stress.perturbation_std", "must be >= 0")
        _require(all(s >= 1 for s in self.scales), "stress.scales", "must be >= 1")

    @property
    def enabled(self) -> bool:
        return bool(self.tests or self.generalisation)


@dataclass
class Config:
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    stress: StressConfig = field(default_factory=StressConfig)
    cconv: CConvConfig = field(default_factory=CConvConfig)  # read when model.architecture = "cconv"
    dpi: DPIConfig = field(default_factory=DPIConfig)  # read when model.architecture = "dpi"

    def validate(self) -> Config:
        self.model.validate()
        self.train.validate()
        self.eval.validate()
        self.stress.validate()
        self.cconv.validate()
        self.dpi.validate()
        return self

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)

    def flat(self) -> dict[str, Any]:
        """Dotted keys, as logged to MLflow params."""
        return {f"{section}.{key}": value for section, values in self.to_dict().items()
                for key, value in values.items()}


def resolve_for_dataset(config: Config, default_connectivity_radius: float) -> Config:
    """`config` with its dataset-dependent defaults filled in, so what is logged, keyed and checkpointed holds
    plain numbers: an unset `model.connectivity_radius` becomes the dataset's R (Sec. 2 / App. B.2; metadata's
    `default_connectivity_radius`). Call it where the dataset is opened; a resolved config is unchanged."""
    if config.model.connectivity_radius is not None:
        return config
    model = dataclasses.replace(config.model, connectivity_radius=float(default_connectivity_radius))
    return dataclasses.replace(config, model=model).validate()


# Model fields added after checkpoints were first written, with the value that rebuilds an older model
# exactly: a config saved before the field existed was trained with this value (see `saved_config`).
LEGACY_MODEL_VALUES: dict[str, Any] = {"aggregate": "updated_edges", "init": "torch",
                                       "type_embedding": "multiple_types", "wall_features": "walls_only"}


def saved_config(data: dict[str, Any], source: str) -> Config:
    """A config read back from a checkpoint or a run: fields it predates take the values its model was
    built with (LEGACY_MODEL_VALUES), not today's defaults, so an old checkpoint loads as what it was."""
    model = dict(data.get("model", {}))
    for key, value in LEGACY_MODEL_VALUES.items():
        model.setdefault(key, value)
    return config_from_dict({**data, "model": model}, source)


def _require(condition: bool, key: str, message: str) -> None:
    if not condition:
        raise ConfigError(f"{key}: {message}")


def _expected(annotation: Any) -> str:
    """What a value of a field's type looks like, for an error message."""
    if typing.get_origin(annotation) is Literal:
        return f"one of {list(typing.get_args(annotation))}"
    return getattr(annotation, "__name__", str(annotation))


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Check `value` against a field's type annotation (bool, int, float, str, Literal, Optional)."""
    origin = typing.get_origin(annotation)
    if origin is Literal:
        if value not in typing.get_args(annotation):
            raise ConfigError(f"{key}: expected one of {list(typing.get_args(annotation))}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(annotation)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg, key)
            except ConfigError as exc:
                errors.append(str(exc))
        if len(errors) == 1:
            raise ConfigError(errors[0])
        raise ConfigError(f"{key}: expected {' or '.join(_expected(a) for a in args if a is not type(None))}, "
                          f"got {value!r}")
    if origin is list:
        (item,) = typing.get_args(annotation)
        if isinstance(value, list | tuple):
            return [_coerce(v, item, key) for v in value]
        raise ConfigError(f"{key}: expected a list, got {value!r}")
    if annotation is bool:
        if isinstance(value, bool):
            return value
    elif annotation is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif annotation is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif annotation is str:
        if isinstance(value, str):
            return value
    else:
        return value
    raise ConfigError(f"{key}: expected {getattr(annotation, '__name__', annotation)}, got {value!r}")


def _parse_override_value(text: str) -> Any:
    """`key=value` overrides take TOML literals (`5`, `1e-4`, `true`, `"scipy"`); bare words are strings."""
    if text.lower() in ("none", "null"):
        return None
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


@functools.cache
def _section_types() -> dict[str, dict[str, Any]]:
    """Each section's field types, resolved once a process: `typing.get_type_hints` evaluates every annotation
    string anew, and reports load configs by the tens of thousands (a committed reports' rebuild spent 60% of
    its time here before)."""
    return {f.name: typing.get_type_hints(type(getattr(Config(), f.name))) for f in dataclasses.fields(Config)}


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> Config:
    config = Config()
    hints_by_section = _section_types()
    for section, values in data.items():
        if section not in hints_by_section:
            raise ConfigError(f"{source}: unknown section [{section}]; expected one of "
                              f"{sorted(hints_by_section)}")
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: [{section}] must be a table")
        target, hints = getattr(config, section), hints_by_section[section]
        for key, value in values.items():
            if key not in hints:
                raise ConfigError(f"{source}: unknown key '{section}.{key}'; known keys: {sorted(hints)}")
            try:
                setattr(target, key, _coerce(value, hints[key], f"{section}.{key}"))
            except ConfigError as exc:
                raise ConfigError(f"{source}: {exc}") from None
    try:
        return config.validate()
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Merge `section.key=value` strings into a nested dict (returns a new dict)."""
    merged = {section: dict(values) for section, values in data.items()}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} has no value: write section.key=value, e.g. "
                              f"{item if '.' in item else 'train.steps'}=1000")
        dotted, raw = item.split("=", 1)
        if dotted.count(".") != 1:
            raise ConfigError(f"override {item!r}: expected section.key=value, e.g. model.latent_size=64")
        section, key = dotted.strip().split(".")
        merged.setdefault(section, {})[key] = _parse_override_value(raw.strip())
    return merged


def read_toml(path: str | Path, error: Callable[[str], Exception] = ConfigError) -> dict[str, Any]:
    """A TOML file (configs, sweeps, domain specs) as a dict. A missing or unparsable file raises
    `error(message)`, the message naming the file and what is wrong with it."""
    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: invalid TOML ({exc})") from None


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    data: dict[str, Any] = {}
    source = "<defaults>"
    if path is not None:
        source = str(path)
        data = read_toml(path)
    if overrides:
        source += " + overrides"
        data = apply_overrides(data, overrides)
    return config_from_dict(data, source)
