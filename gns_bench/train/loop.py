"""The one training loop (paper Sec. 4.3, App. B.3), whatever launches it.

One-step training on noise-corrupted windows: Adam, learning rate decaying exponentially from 1e-4
towards 1e-6, batches of disjoint graphs. Every step's batch and noise come from (seed, step), and a
checkpoint holds model, optimiser and step, so an interrupted run resumes exactly: the loss curve
continues as if it had never stopped.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import json
import math
import statistics
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gns_bench import autotune
from gns_bench import simulators as registry
from gns_bench.config import Config, ConfigError, TrainConfig, resolve_for_dataset, saved_config
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Metadata, Trajectory, load_split, read_metadata
from gns_bench.data.free_fall import falling_frames
from gns_bench.data.windows import GraphBatch, WindowSampler, make_batch
from gns_bench.devices import apply_allocator, load_average, load_limit, resolve_device, set_threads, usable_cores
from gns_bench.model.noise import random_walk_position_noise
from gns_bench.model.simulator import LearnedSimulator, Simulator
from gns_bench.progress import progress_bar
from gns_bench.train import distributed
from gns_bench.train.averaging import WeightAverage, averaged
from gns_bench.train.checkpoints import CHECKPOINT_NAME, build_simulator, load_checkpoint, save_checkpoint
from gns_bench.train.losses import learning_rate, pushed_forward, pushforward_unroll, training_loss  # noqa: F401

# Train settings that may change between an interrupted run and its resumption.
RESUMABLE_CHANGES = {"steps", "checkpoint_every", "log_every", "device", "num_threads", "max_wall_seconds",
                     "eval_every", "eval_trajectories", "eval_rollout_steps", "keep_checkpoints"}
# And between the run that wrote a checkpoint and a run that starts from it (`train.init_from`): how the rate
# ends and which windows are drawn from there (held-still windows added to a trunk trained without them).
BRANCH_CHANGES = RESUMABLE_CHANGES | {"learning_rate_anneal_steps", "learning_rate_anneal_to", "init_from",
                                      "held_share", "weight_average"}


@dataclass
class TrainResult:
    checkpoint: Path
    losses: list[float]  # one per step run by this call
    start_step: int
    final_step: int
    steps_per_second: float
    wall_time_s: float  # training time (`StepClock`) over every call that led to this checkpoint (resumes too)
    eval_seconds: float = 0.0  # spent by this call in periodic evaluation (`on_eval`), not in wall_time_s
    speed: autotune.SpeedSettings | None = None  # the precision and compile setting it trained with
    oversubscribed: str = ""  # when the machine's load exceeded its cores while this call trained (timings off)
    allocator: str = ""  # how the allocator treated freed memory (`train.allocator`, devices.apply_allocator)


def schedule(config: Config) -> Callable[[int], float]:
    """The learning rate by step, as the architecture's spec gives it (the paper's exponential decay, `train.*`,
    unless the simulator brings its own, as CConv does)."""
    return registry.get(config.model.architecture).schedule(config)


def adam(parameters: Iterable[torch.nn.Parameter], lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    """Adam as the paper uses it (eps 1e-8, TensorFlow's and PyTorch's default; CConv's authors use 1e-6); the
    fused kernel where the device has one (the same update, measured 6x faster than the per-tensor loop on the
    bench model's parameters on CPU)."""
    parameters = list(parameters)
    fused = all(p.device.type in ("cpu", "cuda") for p in parameters)
    return torch.optim.Adam(parameters, lr=lr, eps=eps, fused=fused)


def unrolled_steps(config: Config) -> int:
    """Frames after each training window the architecture's loss needs (CConv's authors unroll 2 steps)."""
    return registry.get(config.model.architecture).unrolled_steps(config)


def batch_loss(simulator: Simulator, batch: GraphBatch, position_noise: torch.Tensor, config: Config,
               model: torch.nn.Module | None = None, num_moving: int | None = None, world_size: int = 1,
               precision: str = "fp32", step: int = 0) -> torch.Tensor:
    """The architecture's own training loss on a batch (its `SimulatorSpec.loss`): the GNS's noisy one-step loss
    (`training_loss`), CConv's unrolled one, DPI-Net's on normalised velocities, or a registered model's."""
    spec = registry.get(config.model.architecture)
    return spec.loss(simulator, batch, position_noise, config, model=model, num_moving=num_moving,
                     world_size=world_size, precision=precision, step=step)


def _held_frames(share: float, trajectories: list[Trajectory], metadata: Metadata,
                 dataset_dir: str | Path) -> list[np.ndarray] | None:
    """Each training trajectory's frames a held-still window may come from (`train.held_share`), or None
    without them; a clear error where the dataset cannot give one."""
    if share == 0:
        return None
    where = f"train.held_share = {share} on {dataset_dir}"
    if metadata.gravity is None:
        raise ConfigError(f"{where}: held-still windows fall at the dataset's gravity, and its metadata.json "
                          "has no `gravity`")
    frames = [falling_frames(traj, metadata.gravity) for traj in trajectories]
    if not any(len(f) for f in frames):
        raise ConfigError(f"{where}: no training trajectory has a frame where every moving particle is in free "
                          "fall (data/free_fall.py), so there is no window to hold still")
    return frames


def step_inputs(sampler: WindowSampler, step: int, batch_size: int, noise_std: float,
                rank: int = 0, world_size: int = 1) -> tuple[GraphBatch, torch.Tensor, int]:
    """This process's share of step `step`: its batch, its rows of the noise, the whole batch's moving count.

    Every process draws the same global batch and noise, then keeps its slice, so N processes with
    batch B see exactly what one process with batch N*B sees.
    """
    trajectories, samples = sampler.draw(step, batch_size * world_size)
    sizes = [trajectories[t].num_particles for t, _ in samples]
    moving = torch.from_numpy(np.concatenate([trajectories[t].particle_type for t, _ in samples])
                              != KINEMATIC_PARTICLE_TYPE)
    dim = trajectories[samples[0][0]].position.shape[2]
    noise = random_walk_position_noise((sum(sizes), sampler.window, dim), noise_std,
                                       sampler.noise_generator(step), mask=moving)  # kinematic rows: none
    first = rank * batch_size
    start = sum(sizes[:first])
    mine = samples[first:first + batch_size]
    noise = noise[start:start + sum(sizes[first:first + batch_size])]
    return make_batch(trajectories, mine, sampler.window, future=sampler.future), noise, int(moving.sum())


class LoadWatch:
    """Whether the machine was oversubscribed while a run timed itself: the 1-minute load average sampled at
    each logged step against the usable cores. This run's own threads count in the load, so more than the
    cores means another job competed (two 2-thread jobs on 2 cores made a step about 10x slower), and the
    run's timings are not comparable. Warns once; `report()` says how often and how much for the run's tags."""

    def __init__(self, own_threads: int):
        self.cores = usable_cores()
        self.limit = load_limit(own_threads, self.cores)
        self.samples: list[float] = []

    def sample(self) -> None:
        value = load_average()
        if not math.isfinite(value):
            return
        if value > self.limit and not any(v > self.limit for v in self.samples):
            warnings.warn(f"the machine is oversubscribed: load {value:.1f} on {self.cores} usable cores; another "
                          "job is competing, so this run's step times are not comparable", stacklevel=2)
        self.samples.append(value)

    def report(self) -> str:
        over = [v for v in self.samples if v > self.limit]
        if not over:
            return ""
        return (f"load above {self.limit:g} ({self.cores} cores) at {len(over)} of {len(self.samples)} logged steps, "
                f"up to {max(over):.1f}")


class StepClock:
    """Training time: the sum of step durations, each capped at STALL_FACTOR times the median of the last
    100 steps. A step that stalls (the process stopped with SIGSTOP while something else is timed, another
    job's burst, swapping) adds only a few typical steps' time, so the runs of a budget study get equal
    training time on a machine that is sometimes busy. Checkpoints and periodic evaluation happen between
    steps and are not counted; the first steps (compilation, warm-up) count in full."""

    STALL_FACTOR = 3.0
    WARM_UP = 10  # steps counted in full before the median is trusted

    def __init__(self, earlier: float = 0.0):
        self.total = earlier  # seconds, over every call that led to this run (resumes included)
        self._recent: collections.deque[float] = collections.deque(maxlen=100)

    def add(self, seconds: float) -> float:
        """Count one step that took `seconds`; returns what was counted."""
        counted = seconds
        if len(self._recent) >= self.WARM_UP:
            counted = min(seconds, self.STALL_FACTOR * statistics.median(self._recent))
        self._recent.append(seconds)
        self.total += counted
        return counted


def _speed_settings(config: Config, simulator: Simulator, sampler: WindowSampler, device: torch.device,
                    world_size: int, steps_left: int, saved: autotune.SpeedSettings | None = None
                    ) -> autotune.SpeedSettings:
    """The precision and compile setting to train with, and with `train.num_threads = "auto"` the thread count
    (set here): the config's, or for "auto" the fastest on this machine (`autotune.choose_threads`, then
    `autotune.choose` at that count). A resumed run trains on with the settings it `saved`; only a thread count
    it never chose (it trained on a given count, or before the setting existed) is probed now. Under data
    parallelism every rank must agree without a probe of its own: "auto" trains in fp32, uncompiled, on every
    core of the rank."""
    tc = config.train
    probe_threads = tc.num_threads == "auto" and device.type == "cpu" and world_size == 1
    if saved is not None and (saved.threads is not None or not probe_threads):
        return saved
    if world_size > 1:
        return autotune.SpeedSettings("fp32" if tc.precision == "auto" else tc.precision,
                                      False if tc.compile == "auto" else bool(tc.compile))
    optimisers: dict[int, torch.optim.Optimizer] = {}
    batch, noise, num_moving = step_inputs(sampler, 0, tc.batch_size, tc.noise_std)
    batch, noise = batch.to(device), noise.to(device)

    def probe_step(model: LearnedSimulator, precision: str) -> None:
        optimiser = optimisers.setdefault(id(model), adam(model.parameters(), 0.0))  # lr 0: timing only
        loss = batch_loss(model, batch, noise, config, model, num_moving, 1, precision)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        float(loss.detach())

    nodes = batch.window.shape[0]
    threads = None
    if probe_threads:  # before the precision probe: its timings depend on it
        precision = saved.precision if saved else "fp32" if tc.precision == "auto" else tc.precision
        model, key = copy.deepcopy(simulator), f"{autotune.cache_key(tc, simulator, nodes, device)} | {precision}"
        threads = autotune.choose_threads(lambda: probe_step(model, precision), key, usable_cores())
        del model
    speed = saved or autotune.choose(tc, simulator, probe_step, nodes, device, steps_left)
    return dataclasses.replace(speed, threads=threads)


def load_training_split(config: Config, dataset_dir: str | Path, metadata: Metadata) -> list[Trajectory]:
    """The train split, validated (`load_split` reports the first bad file, trajectory and field)."""
    return load_split(dataset_dir, "train", metadata, min_length=config.model.input_sequence_length + 1)


def check_resumable(path: Path, config: Config, metadata: Metadata, branch: bool = False) -> dict:
    """The checkpoint at `path`, loaded, if `config` on `metadata`'s dataset can resume from it (`branch`: start
    from it, `train.init_from`); raises otherwise (callers check this before they open anything a failure would
    leave behind)."""
    saved = load_checkpoint(path, "cpu")
    _check_resumable(saved, config, metadata, path, BRANCH_CHANGES if branch else RESUMABLE_CHANGES)
    return saved


def _check_resumable(saved: dict, config: Config, metadata: Metadata, path: Path,
                     may_change: set[str] = RESUMABLE_CHANGES) -> None:
    if saved["metadata"].get("content_hash") != metadata.content_hash:
        raise ValueError(f"{path}: checkpoint was trained on dataset {saved['metadata'].get('content_hash')}, "
                         f"not {metadata.content_hash}")
    old = resolve_for_dataset(saved_config(saved["config"], str(path)), metadata.default_connectivity_radius)
    if old.model != config.model:
        raise ValueError(f"{path}: model config differs from the checkpoint's; cannot resume")
    changed = {f.name for f in dataclasses.fields(TrainConfig)
               if getattr(old.train, f.name) != getattr(config.train, f.name)} - may_change
    if changed:
        raise ValueError(f"{path}: train settings {sorted(changed)} differ from the checkpoint's; cannot resume")


def train(config: Config, dataset_dir: str | Path, out_dir: str | Path, *, resume: bool = False,
          on_log: Callable[[int, dict[str, float]], None] | None = None,
          progress: bool = True, trajectories: list[Trajectory] | None = None,
          on_eval: Callable[[LearnedSimulator, int, float], None] | None = None,
          stop_after: int | None = None) -> TrainResult:
    """Train to `config.train.steps` (or `train.max_wall_seconds`), checkpointing into `out_dir`.

    `on_log(step, metrics)` gets the loss. `on_eval(simulator, step, training_seconds)` gets, every
    `train.eval_every` steps and at the end (and at step 0 of a fresh run), an uncompiled copy of the model in
    eval mode; its time is not training time. `trajectories`: the dataset's train split when the caller has
    loaded (and so validated) it already. `stop_after`: return after this many steps of this call, as part of a
    run of `train.steps` (the step-rate probe, `gns_bench/train/rate.py`: the run's own settings and schedule).

    Launched by torchrun (WORLD_SIZE > 1), it trains data-parallel: each process takes
    `train.batch_size` graphs of every step's batch; only rank 0 logs and writes checkpoints.
    """
    tc = config.train
    threads = set_threads(None if tc.num_threads == "auto" else tc.num_threads)  # "auto": chosen below
    allocator = apply_allocator(tc.allocator)
    device = resolve_device(tc.device)
    group = distributed.from_environment(device)
    progress = progress and group.is_main
    metadata = read_metadata(dataset_dir)
    config = resolve_for_dataset(config, metadata.default_connectivity_radius)
    if trajectories is None:
        trajectories = load_training_split(config, dataset_dir, metadata)
    held_frames = _held_frames(tc.held_share, trajectories, metadata, dataset_dir)
    sampler = WindowSampler(trajectories, config.model.input_sequence_length, tc.seed, unrolled_steps(config),
                            tc.start_window_share, tc.start_windows, tc.held_share, held_frames, metadata.gravity)

    torch.manual_seed(tc.seed)
    simulator = build_simulator(config, metadata).to(device)
    rate = schedule(config)
    spec = registry.get(config.model.architecture)
    if not spec.data_parallel and group.world_size > 1:
        raise ConfigError("data-parallel training (torchrun) covers the GNS only, not model.architecture = "
                          f"{config.model.architecture!r}")
    optimiser = adam(simulator.parameters(), rate(0), spec.adam_eps(config))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_path = out_dir / CHECKPOINT_NAME
    step, earlier_wall_time, saved_speed, resumed_window, saved_average = 0, 0.0, None, [], None
    curve_step = 0  # the last step whose curve point (train.eval_every) was logged
    start_from = (checkpoint_path if resume and checkpoint_path.exists()
                  else Path(tc.init_from) if tc.init_from and not checkpoint_path.exists() else None)
    if start_from is not None:  # a resume, or a branch from another run's checkpoint
        saved = load_checkpoint(start_from, device)
        _check_resumable(saved, config, metadata, start_from,
                         RESUMABLE_CHANGES if start_from == checkpoint_path else BRANCH_CHANGES)
        simulator.load_state_dict(saved["model"])
        optimiser.load_state_dict(saved["optimizer"])
        saved_average = saved.get("average")  # a branch from a trunk without one starts it from its weights
        step = int(saved["step"])
        earlier_wall_time = float(saved.get("wall_time_s", 0.0))
        if "speed" in saved:  # a resumed run trains on with the settings it chose
            saved_speed = autotune.SpeedSettings.from_dict(saved["speed"])
        # the losses since the last logged point, so the next point averages the same steps as without a stop
        resumed_window = [float(v) for v in saved.get("log_window", [])]
        # a resume evaluates the curve point a stop cut short; a branch starts where its trunk's curve has it
        # (a checkpoint from before the field: taken as logged)
        curve_step = int(saved.get("curve_step", step)) if start_from == checkpoint_path else step
    elif checkpoint_path.exists():
        raise FileExistsError(f"{checkpoint_path} exists; pass resume=True (--resume) or choose another out dir")
    average = WeightAverage(simulator, tc.weight_average) if tc.weight_average else None
    if average is not None and saved_average is not None:
        average.load_state_dict(saved_average)
    speed = _speed_settings(config, simulator, sampler, device, group.world_size, tc.steps - step, saved_speed)
    if speed.threads is not None and tc.num_threads == "auto":  # chosen now, or by the run this resumes
        threads = set_threads(speed.threads.threads)
    if speed.compile:
        simulator.network.compile(dynamic=True)  # in place: parameter names and checkpoints unchanged
    model = group.wrap(simulator)
    if group.is_main:
        (out_dir / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n")

    paused = 0.0  # seconds of this call spent in periodic evaluation
    clock = StepClock(earlier_wall_time)
    load = LoadWatch(threads if device.type == "cpu" else 1)

    def training_seconds() -> float:
        return clock.total

    def checkpoint(at_step: int, path: Path = checkpoint_path) -> None:
        if not group.is_main:
            return
        save_checkpoint(path, {
            "model": simulator.state_dict(), "optimizer": optimiser.state_dict(), "step": at_step,
            "config": config.to_dict(), "metadata": metadata.to_json(), "dataset": str(dataset_dir),
            "wall_time_s": training_seconds(), "speed": dataclasses.asdict(speed), "log_window": list(window_losses),
            "curve_step": curve_step, **({"average": average.state_dict()} if average is not None else {})})

    def evaluate_now(at_step: int) -> None:
        nonlocal paused, curve_step
        if on_eval is None or not group.is_main:
            return
        seconds, began = clock.total, time.perf_counter()
        snapshot = build_simulator(config, metadata).to(device)  # uncompiled, whatever trains
        snapshot.load_state_dict(averaged(simulator.state_dict(), average.state_dict() if average else None))
        on_eval(snapshot.eval(), at_step, seconds)
        curve_step = at_step
        paused += time.perf_counter() - began

    start_step, losses, window_losses = step, [], resumed_window
    bar = progress_bar(total=tc.steps, initial=step, disable=not progress, unit="step", dynamic_ncols=True,
               desc="train")
    evaluating = on_eval is not None and tc.eval_every > 0
    if evaluating and (step == 0 or (curve_step < step and (step % tc.eval_every == 0 or step >= tc.steps))):
        evaluate_now(step)  # a fresh run's first point, or the point a stop cut short (its checkpoint came first)
    simulator.train()
    try:
        while step < tc.steps and (stop_after is None or step - start_step < stop_after):
            if tc.max_wall_seconds is not None and clock.total >= tc.max_wall_seconds:
                break
            step_started = time.perf_counter()
            lr = rate(step)
            for param_group in optimiser.param_groups:
                param_group["lr"] = lr
            batch, noise, num_moving = step_inputs(sampler, step, tc.batch_size, tc.noise_std, group.rank,
                                                   group.world_size)
            loss = batch_loss(simulator, batch.to(device), noise.to(device), config, model, num_moving,
                              group.world_size, speed.precision, step)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            if average is not None:
                average.update()
            step += 1
            value = float(loss.detach())  # waits for the step to finish (a GPU's too)
            clock.add(time.perf_counter() - step_started)
            losses.append(value)
            window_losses.append(value)
            bar.update(1)
            if step % tc.log_every == 0 or step == tc.steps:
                load.sample()
                mean_loss = sum(window_losses) / len(window_losses)
                window_losses = []
                bar.set_postfix(loss=f"{mean_loss:.3g}", lr=f"{lr:.2g}")
                if on_log and group.is_main:
                    on_log(step, {"train_loss": mean_loss, "learning_rate": lr})
            if step % tc.checkpoint_every == 0:
                checkpoint(step)
            if evaluating and step % tc.eval_every == 0:
                if tc.keep_checkpoints:  # a point a branch can start from
                    checkpoint(step, out_dir / f"checkpoint-{step}.pt")
                evaluate_now(step)
                simulator.train()
    except KeyboardInterrupt:
        checkpoint(step)  # every completed step is kept; resume with --resume
        raise
    finally:
        bar.close()
        del model  # a DDP wrapper must go before its process group (ProcessGroup.close), even on Ctrl-C
    checkpoint(step)
    if evaluating and step % tc.eval_every and step > start_step:  # the last point of the curve
        evaluate_now(step)
    group.close()
    elapsed = clock.total - earlier_wall_time
    rate = (step - start_step) / elapsed if elapsed > 0 and step > start_step else 0.0
    return TrainResult(checkpoint_path, losses, start_step, step, rate, clock.total, paused, speed, load.report(),
                       allocator)
