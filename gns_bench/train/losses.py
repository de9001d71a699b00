"""The GNS's training losses and learning rate (paper Sec. 4.3, App. B.3): pure functions of a batch, a model
and a step, shared by the training loop and the simulator registry (`gns_bench/simulators.py`)."""

from __future__ import annotations

import numpy as np
import torch

from gns_bench.config import TrainConfig
from gns_bench.data.windows import GraphBatch
from gns_bench.model.features import acceleration_from_next_position
from gns_bench.model.noise import noisy_training_pair
from gns_bench.model.precision import autocast
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask


def learning_rate(step: int, config: TrainConfig) -> float:
    """The paper's exponential decay (App. B.3), after a linear warm-up where one is set, and where an anneal is
    set, falling linearly over the last `learning_rate_anneal_steps` steps from the rate where it begins to
    `learning_rate_anneal_to` at step `steps`."""
    def decayed(at: int) -> float:
        decay = 0.1 ** (at / config.learning_rate_decay_steps)
        return (config.learning_rate - config.learning_rate_final) * decay + config.learning_rate_final

    anneal_from = config.steps - config.learning_rate_anneal_steps
    if config.learning_rate_anneal_steps and step >= anneal_from:
        done = (step - anneal_from) / config.learning_rate_anneal_steps
        rate = decayed(anneal_from) + (config.learning_rate_anneal_to - decayed(anneal_from)) * done
    else:
        rate = decayed(step)
    if step < config.learning_rate_warmup_steps:
        rate *= (step + 1) / config.learning_rate_warmup_steps
    return rate


def pushforward_unroll(config: TrainConfig, step: int) -> int:
    """How many steps the model rolls itself forward before training step `step` (`train.pushforward_*`): 0
    before `pushforward_start` and on the other steps, else 1..`pushforward_steps`, drawn from the seed and the
    step alone (a resumed run draws the same)."""
    if config.pushforward_steps <= 0 or step < config.pushforward_start:
        return 0
    rng = np.random.default_rng([config.seed, step, 0x9F])
    return int(rng.integers(1, config.pushforward_steps + 1)) if rng.random() < config.pushforward_share else 0


@torch.no_grad()
def pushed_forward(simulator: LearnedSimulator, window: torch.Tensor, batch: GraphBatch, unroll: int,
                   precision: str, moving_only: bool = False,
                   position_correction: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The (noisy) window rolled forward `unroll` >= 1 steps by the model, without gradient (kinematic
    particles on their true paths), and the target after it: `batch.future` holds the frames after the window
    (the sampler draws 1 + `train.pushforward_steps` of them).

    The target treats the pushed window's departure from the truth as the noise target correction treats the
    input noise (Sec. 4.3, App. C.2; `noisy_training_pair`): p*_{k+1} = p_{k+1} + (1 - alpha) (p~_k - p_k), p~_k
    the pushed last position and p_k the true one. With alpha = 0 (the paper's default) the model is asked for
    the true next velocity from where its own rollout stands, as on an unpushed step; alpha = 1 asks it to land on
    the true position, undoing the whole drift in one step (on GOOP that made unrolled steps' loss 10-40x an
    unpushed step's)."""
    future = batch.future if batch.future is not None else batch.target[:, None]
    kinematic = kinematic_mask(batch.particle_type)[:, None]
    for k in range(unroll):
        predicted = simulator.predict_next_position(window, batch.particle_type, batch.batch, batch.context,
                                                    precision=precision, moving_only=moving_only)
        predicted = torch.where(kinematic, future[:, k], predicted.to(window.dtype))
        window = torch.cat([window[:, 1:], predicted[:, None]], dim=1)
    drift = window[:, -1] - future[:, unroll - 1]
    return window, future[:, unroll] + (1.0 - position_correction) * drift


def training_loss(simulator: LearnedSimulator, batch: GraphBatch, position_noise: torch.Tensor,
                  position_correction: float, model: torch.nn.Module | None = None,
                  num_moving: int | None = None, world_size: int = 1, precision: str = "fp32",
                  unroll: int = 0, moving_only: bool = False) -> torch.Tensor:
    """Squared error of normalised accelerations, summed over dims, averaged over non-kinematic particles.

    `position_noise` is `step_inputs`' (kinematic rows zero: they follow the data, Sec. 4.3).
    `model` is what runs the forward pass (the simulator itself, or its DistributedDataParallel wrapper).
    Under data parallelism each process holds part of the batch: dividing by the whole batch's
    `num_moving` and multiplying by `world_size` makes the gradient average across processes equal the
    single-process gradient of the whole batch.
    `moving_only`: kinematic particles' predictions, which the loss leaves out, are not computed
    (`LearnedSimulator.forward`); the same loss and gradients up to float rounding.
    """
    moving = ~kinematic_mask(batch.particle_type)
    window, target_next = noisy_training_pair(batch.window, batch.target, position_noise, position_correction)
    if unroll:  # pushforward: the model's own predictions make the window, the target corrected as for noise
        window, target_next = pushed_forward(simulator, window, batch, unroll, precision, moving_only,
                                             position_correction)
    target = simulator.normalise_acceleration(acceleration_from_next_position(window, target_next))
    with autocast(window.device, precision):
        predicted = (model or simulator)(window, batch.particle_type, batch.batch, batch.context,
                                         moving_only=moving_only).float()
    per_particle = (predicted - target).square().sum(dim=-1)
    denominator = max(int(moving.sum()) if num_moving is None else num_moving, 1)
    return (per_particle * moving).sum() * (world_size / denominator)
