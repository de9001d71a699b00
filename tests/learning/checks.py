"""Train the paper's GNS briefly on the blocks of `scenes.py` and measure it against the known answers.

The model is small (latent 32, 3 message-passing steps: the blocks are 1.5 R tall) and trained with the
paper's pipeline end to end: `metadata.json` statistics computed from the data, the feature pipeline, the
random-walk noise at the paper's sigma_v = 3e-4 with its target correction, the masked loss, Adam; then
gns-bench's own rollout and diagnostics (`gns_bench/evaluate/diagnostics.py`) score it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scenes
import torch

from gns_bench.config import config_from_dict
from gns_bench.data.format import Trajectory
from gns_bench.evaluate import diagnostics
from gns_bench.evaluate.rollout import rollout
from gns_bench.model.simulator import LearnedSimulator
from gns_bench.train.checkpoints import load_simulator
from gns_bench.train.loop import train

FRAMES = 110  # a free-falling block stays in the air for the whole check's 100-step rollout
TRAIN_TRAJECTORIES = 24
STEPS = 6000
TRAIN_KINDS = ("free_fall", "drop", "rest", "landing")


def dataset(root: Path, seed: int = 0, **stat_changes: list[float]) -> Path:
    """The training set (blocks of every kind) with a held-out test split of free-falling blocks."""
    rng = np.random.default_rng(seed)
    train_set = scenes.mixed_split(rng, TRAIN_TRAJECTORIES, FRAMES, kinds=TRAIN_KINDS)
    valid = scenes.mixed_split(rng, 1, FRAMES, kinds=TRAIN_KINDS)
    test = [scenes.trajectory(rng, ["free_fall", "drop", "free_fall", "drop"], FRAMES) for _ in range(2)]
    return scenes.write(root, train_set, valid, test, **stat_changes)


def trained(data: Path, out: Path, precision: str = "fp32", steps: int = STEPS, **overrides: dict) -> LearnedSimulator:
    """The paper's GNS, small, trained `steps` steps on `data`; `overrides` change config sections."""
    config = {"model": {"latent_size": 32, "mlp_hidden_size": 32, "message_passing_steps": 3},
              "train": {"steps": steps, "learning_rate": 1e-3, "learning_rate_final": 1e-5,
                        "learning_rate_decay_steps": steps, "log_every": 500, "checkpoint_every": steps,
                        "precision": precision, "compile": False, "seed": 0}}
    for section, values in overrides.items():
        config[section] = {**config.get(section, {}), **values}
    result = train(config_from_dict(config), data, out, progress=False)
    simulator, _, _ = load_simulator(result.checkpoint)
    return simulator


@dataclass
class FreeFall:
    mean_ratio: float  # mean over particles and windows of the predicted vertical acceleration over g
    particle_ratios: np.ndarray  # per particle, averaged over windows
    rollout_error: float  # the largest distance of a particle from its parabola after 100 steps, in R
    com_fall_ratios: list[float]  # per block: predicted fall of its centre over the true one after 100 steps


@torch.no_grad()
def free_fall(simulator: LearnedSimulator, trajectories: list[Trajectory], precision: str = "fp32",
              steps: int = 100) -> FreeFall:
    """One-step accelerations on the true windows of free-falling blocks against g, and a rollout against the
    parabola (every particle of these trajectories is in free fall throughout)."""
    w = simulator.input_sequence_length
    g = scenes.GRAVITY[1]
    per_particle, errors, falls = [], [], []
    for traj in trajectories:
        ratios = []
        for t in range(w - 1, traj.num_steps - 1, 5):
            window = torch.from_numpy(traj.position[t - w + 1: t + 1]).transpose(0, 1).contiguous()
            nxt = simulator.predict_next_position(window, torch.from_numpy(traj.particle_type), precision=precision)
            acc = (nxt.double() - 2 * window[:, -1].double() + window[:, -2].double())[:, 1].numpy()
            ratios.append(acc / g)
        per_particle.append(np.mean(ratios, axis=0))
        result = rollout(simulator, traj, steps, precision=precision)
        errors.append(np.linalg.norm(result.predicted[-1] - result.ground_truth[-1], axis=-1).max() / scenes.RADIUS)
        block = scenes.COLUMNS * scenes.ROWS
        for start in range(0, traj.num_particles, block):
            moving = np.zeros(traj.num_particles, bool)
            moving[start: start + block] = True
            com = diagnostics.centre_of_mass_errors(result.initial_window, result.predicted, result.ground_truth,
                                                    moving, scenes.GRAVITY, min_fall=scenes.RADIUS)
            falls.append(com["com_fall_ratio"])
    particles = np.concatenate(per_particle)
    return FreeFall(float(particles.mean()), particles, float(max(errors)), falls)


@dataclass
class Support:
    max_deviation: float  # the largest distance of a particle from the truth over the rollout, in R
    below_floor: int  # particles that end a step below the floor (through the wall)
    lowest_gap: float  # the lowest particle's height above the floor over the rollout, in R


@torch.no_grad()
def supported(simulator: LearnedSimulator, kind: str, precision: str = "fp32", steps: int = 200,
              seed: int = 7) -> Support:
    """Blocks of `kind` ("rest": on the floor from the start; "landing": falling onto it) rolled out `steps`
    steps against the truth, which keeps them above the floor at rest."""
    rng = np.random.default_rng(seed)
    traj = scenes.trajectory(rng, [kind] * 4, steps + simulator.input_sequence_length)
    result = rollout(simulator, traj, steps, precision=precision)
    y = result.predicted[..., 1]
    return Support(float(np.linalg.norm(result.predicted - result.ground_truth, axis=-1).max() / scenes.RADIUS),
                   int((y < scenes.FLOOR).any(axis=0).sum()), float((y.min() - scenes.FLOOR) / scenes.RADIUS))
