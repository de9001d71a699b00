"""`tiny`: a built-in domain that needs no physics engine, for tests and the quickstart.

Balls fall under gravity in a unit box and bounce off its walls, which push back as damped springs
within a contact distance (smooth accelerations a network can learn from its wall-distance
features); a row of static boundary particles (kinematic type 3) lines the floor. Balls do not
interact with each other. Made in well under a second.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Metadata, Trajectory, write_dataset
from gns_bench.data.statistics import compute_statistics

TINY = "tiny"  # this domain's id
BOUNDS = np.array([[0.0, 1.0], [0.0, 1.0]])
RADIUS = 0.1
GRAVITY = np.array([0.0, -4e-4])  # per stored frame squared
WALL_STIFFNESS = 0.4  # per frame squared: a contact lasts about pi / sqrt(k) ~ 5 frames
WALL_DAMPING = 0.1  # per frame
CONTACT = 0.05  # walls push within this distance of the bounds (half of R)
SUBSTEPS = 20
WATER = 5

TIERS = {  # trajectories per split, balls, frames
    "smoke": {"train": 8, "valid": 2, "test": 2, "balls": 24, "frames": 60},
    "small": {"train": 64, "valid": 8, "test": 8, "balls": 48, "frames": 150},
    "cpu": {"train": 64, "valid": 8, "test": 8, "balls": 48, "frames": 150},
}


def simulate(rng: np.random.Generator, num_balls: int, num_frames: int) -> Trajectory:
    lo, hi = BOUNDS[:, 0] + CONTACT, BOUNDS[:, 1] - CONTACT
    pos = np.stack([rng.uniform(0.1, 0.9, num_balls), rng.uniform(0.4, 0.9, num_balls)], axis=1)
    vel = rng.normal(0.0, 4e-3, size=(num_balls, 2))
    frames = [pos.copy()]
    h = 1.0 / SUBSTEPS
    for _ in range(num_frames - 1):
        for _ in range(SUBSTEPS):
            penetration = np.maximum(lo - pos, 0.0) - np.maximum(pos - hi, 0.0)  # signed, inwards
            wall = WALL_STIFFNESS * penetration - WALL_DAMPING * vel * (penetration != 0)
            vel = vel + (GRAVITY + wall) * h  # semi-implicit Euler substeps
            pos = pos + vel * h
        frames.append(pos.copy())
    floor = np.stack([np.linspace(0.0, 1.0, 11), np.zeros(11)], axis=1)
    balls = np.stack(frames).astype(np.float32)
    walls = np.broadcast_to(floor, (num_frames, 11, 2)).astype(np.float32)
    types = np.concatenate([np.full(num_balls, WATER), np.full(11, KINEMATIC_PARTICLE_TYPE)])
    return Trajectory(np.concatenate([balls, walls], axis=1), types.astype(np.int64))


def generate_tiny(out: str | Path, tier: str = "smoke", seed: int = 0, overwrite: bool = False) -> Path:
    if tier not in TIERS:
        raise ValueError(f"tiny domain: unknown tier {tier!r}; expected one of {sorted(TIERS)}")
    spec = TIERS[tier]
    splits = {}
    for index, split in enumerate(("train", "valid", "test")):
        rng = np.random.default_rng([seed, index])
        splits[split] = [simulate(rng, spec["balls"], spec["frames"]) for _ in range(spec[split])]
    stats = compute_statistics(splits["train"])
    meta = Metadata(
        bounds=BOUNDS.tolist(), sequence_length=spec["frames"] - 1, default_connectivity_radius=RADIUS,
        dim=2, dt=0.01, **stats, name=TINY, particle_types={"water": WATER, "kinematic": KINEMATIC_PARTICLE_TYPE},
        walls=True, gravity=GRAVITY.tolist(),
        generator={"name": "gns-bench", "domain": TINY, "tier": tier, "seed": seed, "solver": "analytic"},
    )
    return write_dataset(out, meta, splits, overwrite=overwrite)
