"""The one training loop (paper Sec. 4.3, App. B.3), whatever launches it.

One-step training on noise-corrupted windows: Adam, learning rate decaying exponentially from 1e-4
towards 1e-6, batches of disjoint graphs. Every step's batch and noise come from (seed, step), and a
checkpoint holds model, optimiser and step, so an interrupted run resumes exactly: the loss curve
continues as if it had never stopped.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from gns_bench.config import Config, TrainConfig, resolve_for_dataset, saved_config
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Metadata, load_split, read_metadata
from gns_bench.data.windows import GraphBatch, WindowSampler, make_batch
from gns_bench.devices import resolve_device
from gns_bench.model.features import acceleration_from_next_position
from gns_bench.model.noise import noisy_training_pair, random_walk_position_noise
from gns_bench.model.precision import autocast
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask
from gns_bench.train import distributed
from gns_bench.train.checkpoints import CHECKPOINT_NAME, build_simulator, load_checkpoint, save_checkpoint

# Train settings that may change between an interrupted run and its resumption.
RESUMABLE_CHANGES = {"steps", "checkpoint_every", "log_every", "device", "num_threads"}


@dataclass
class TrainResult:
    checkpoint: Path
    losses: list[float]  # one per step run by this call
    start_step: int
    final_step: int
    steps_per_second: float
    wall_time_s: float  # training time over every call that led to this checkpoint (resumes included)


def learning_rate(step: int, config: TrainConfig) -> float:
    decay = 0.1 ** (step / config.learning_rate_decay_steps)
    return (config.learning_rate - config.learning_rate_final) * decay + config.learning_rate_final


def adam(parameters: Iterable[torch.nn.Parameter], lr: float) -> torch.optim.Adam:
    """Adam as the paper uses it; the fused kernel where the device has one (the same update, measured
    6x faster than the per-tensor loop on the bench model's parameters on CPU)."""
    parameters = list(parameters)
    fused = all(p.device.type in ("cpu", "cuda") for p in parameters)
    return torch.optim.Adam(parameters, lr=lr, fused=fused)


def training_loss(simulator: LearnedSimulator, batch: GraphBatch, position_noise: torch.Tensor,
                  position_correction: float, model: torch.nn.Module | None = None,
                  num_moving: int | None = None, world_size: int = 1, precision: str = "fp32") -> torch.Tensor:
    """Squared error of normalised accelerations, summed over dims, averaged over non-kinematic particles.

    `model` is what runs the forward pass (the simulator itself, or its DistributedDataParallel wrapper).
    Under data parallelism each process holds part of the batch: dividing by the whole batch's
    `num_moving` and multiplying by `world_size` makes the gradient average across processes equal the
    single-process gradient of the whole batch.
    """
    moving = ~kinematic_mask(batch.particle_type)
    noise = position_noise * moving[:, None, None]  # kinematic particles are never noised
    window, target_next = noisy_training_pair(batch.window, batch.target, noise, position_correction)
    target = simulator.normalise_acceleration(acceleration_from_next_position(window, target_next))
    with autocast(window.device, precision):
        predicted = (model or simulator)(window, batch.particle_type, batch.batch, batch.context).float()
    per_particle = (predicted - target).square().sum(dim=-1)
    denominator = max(int(moving.sum()) if num_moving is None else num_moving, 1)
    return (per_particle * moving).sum() * (world_size / denominator)


def step_inputs(sampler: WindowSampler, step: int, batch_size: int, noise_std: float,
                rank: int = 0, world_size: int = 1) -> tuple[GraphBatch, torch.Tensor, int]:
    """This process's share of step `step`: its batch, its rows of the noise, the whole batch's moving count.

    Every process draws the same global batch and noise, then keeps its slice, so N processes with
    batch B see exactly what one process with batch N*B sees.
    """
    samples = sampler.samples(step, batch_size * world_size)
    sizes = [sampler.trajectories[t].num_particles for t, _ in samples]
    num_moving = sum(int((sampler.trajectories[t].particle_type != KINEMATIC_PARTICLE_TYPE).sum())
                     for t, _ in samples)
    dim = sampler.trajectories[samples[0][0]].position.shape[2]
    noise = random_walk_position_noise((sum(sizes), sampler.window, dim), noise_std,
                                       sampler.noise_generator(step))
    first = rank * batch_size
    start = sum(sizes[:first])
    mine = samples[first:first + batch_size]
    noise = noise[start:start + sum(sizes[first:first + batch_size])]
    return make_batch(sampler.trajectories, mine, sampler.window), noise, num_moving


def _check_resumable(saved: dict, config: Config, metadata: Metadata, path: Path) -> None:
    if saved["metadata"].get("content_hash") != metadata.content_hash:
        raise ValueError(f"{path}: checkpoint was trained on dataset {saved['metadata'].get('content_hash')}, "
                         f"not {metadata.content_hash}")
    old = resolve_for_dataset(saved_config(saved["config"], str(path)), metadata.default_connectivity_radius)
    if old.model != config.model:
        raise ValueError(f"{path}: model config differs from the checkpoint's; cannot resume")
    changed = {f.name for f in dataclasses.fields(TrainConfig)
               if getattr(old.train, f.name) != getattr(config.train, f.name)} - RESUMABLE_CHANGES
    if changed:
        raise ValueError(f"{path}: train settings {sorted(changed)} differ from the checkpoint's; cannot resume")


def train(config: Config, dataset_dir: str | Path, out_dir: str | Path, *, resume: bool = False,
          on_log: Callable[[int, dict[str, float]], None] | None = None,
          progress: bool = True) -> TrainResult:
    """Train to `config.train.steps`, checkpointing into `out_dir`. `on_log(step, metrics)` gets the loss.

    Launched by torchrun (WORLD_SIZE > 1), it trains data-parallel: each process takes
    `train.batch_size` graphs of every step's batch; only rank 0 logs and writes checkpoints.
    """
    tc = config.train
    if tc.num_threads:
        torch.set_num_threads(tc.num_threads)
    device = resolve_device(tc.device)
    group = distributed.from_environment(device)
    progress = progress and group.is_main
    metadata = read_metadata(dataset_dir)
    config = resolve_for_dataset(config, metadata.default_connectivity_radius)
    trajectories = load_split(dataset_dir, "train", metadata, min_length=config.model.input_sequence_length + 1)
    sampler = WindowSampler(trajectories, config.model.input_sequence_length, tc.seed)

    torch.manual_seed(tc.seed)
    simulator = build_simulator(config, metadata).to(device)
    if tc.compile:
        simulator.network.compile(dynamic=True)  # in place: parameter names and checkpoints unchanged
    model = group.wrap(simulator)
    optimiser = adam(simulator.parameters(), learning_rate(0, tc))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_path = out_dir / CHECKPOINT_NAME
    step, earlier_wall_time = 0, 0.0
    if resume and checkpoint_path.exists():
        saved = load_checkpoint(checkpoint_path, device)
        _check_resumable(saved, config, metadata, checkpoint_path)
        simulator.load_state_dict(saved["model"])
        optimiser.load_state_dict(saved["optimizer"])
        step = int(saved["step"])
        earlier_wall_time = float(saved.get("wall_time_s", 0.0))
    elif checkpoint_path.exists():
        raise FileExistsError(f"{checkpoint_path} exists; pass resume=True (--resume) or choose another out dir")
    if group.is_main:
        (out_dir / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n")

    def checkpoint(at_step: int) -> None:
        if not group.is_main:
            return
        save_checkpoint(checkpoint_path, {
            "model": simulator.state_dict(), "optimizer": optimiser.state_dict(), "step": at_step,
            "config": config.to_dict(), "metadata": metadata.to_json(), "dataset": str(dataset_dir),
            "wall_time_s": earlier_wall_time + time.perf_counter() - started})

    start_step, losses, window_losses = step, [], []
    bar = tqdm(total=tc.steps, initial=step, disable=not progress, unit="step", dynamic_ncols=True,
               desc="train")
    started = time.perf_counter()
    simulator.train()
    try:
        while step < tc.steps:
            lr = learning_rate(step, tc)
            for param_group in optimiser.param_groups:
                param_group["lr"] = lr
            batch, noise, num_moving = step_inputs(sampler, step, tc.batch_size, tc.noise_std, group.rank,
                                                   group.world_size)
            loss = training_loss(simulator, batch.to(device), noise.to(device), tc.position_correction, model,
                                 num_moving, group.world_size, tc.precision)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            step += 1
            value = float(loss.detach())
            losses.append(value)
            window_losses.append(value)
            bar.update(1)
            if step % tc.log_every == 0 or step == tc.steps:
                mean_loss = sum(window_losses) / len(window_losses)
                window_losses = []
                bar.set_postfix(loss=f"{mean_loss:.3g}", lr=f"{lr:.2g}")
                if on_log and group.is_main:
                    on_log(step, {"train_loss": mean_loss, "learning_rate": lr})
            if step % tc.checkpoint_every == 0:
                checkpoint(step)
    except KeyboardInterrupt:
        checkpoint(step)  # every completed step is kept; resume with --resume
        raise
    finally:
        bar.close()
        del model  # a DDP wrapper must go before its process group (ProcessGroup.close), even on Ctrl-C
    checkpoint(step)
    group.close()
    elapsed = time.perf_counter() - started
    rate = (step - start_step) / elapsed if elapsed > 0 and step > start_step else 0.0
    return TrainResult(checkpoint_path, losses, start_step, step, rate, earlier_wall_time + elapsed)
