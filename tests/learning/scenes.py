"""Ground truth with known answers for the learning checks: rigid blocks of particles in a 2D box.

Each block moves as one rigid body under gravity; the floor (the lower y bound) pushes a block whose lowest row
comes within `CONTACT` of it with a damped spring (integrated in substeps), so a block in the air has exactly
g * dt^2 as every particle's acceleration (free fall), a block resting on the floor has none, and a falling
block decelerates over a few frames when it lands and then rests. The scales are WaterDrop's (App. B.1 and
the released metadata.json): g * dt^2 = 9.81 * 0.0025^2 per frame squared, R = 0.015, particles half R apart,
so the model meets the same signal-to-noise as on the MPM domains: gravity is 0.2 of the training noise
sigma_v = 3e-4 per frame. Blocks are far apart (no block sees another), and each trajectory mixes blocks
in the air and on the floor, so that a model must tell them apart from what its graph carries: the wall
distance of the lowest row, passed up by message passing, and the velocity history.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gns_bench.data.format import Metadata, Trajectory, write_dataset
from gns_bench.data.statistics import compute_statistics

BOUNDS = np.array([[0.1, 0.9], [0.1, 0.9]])
FLOOR = BOUNDS[1, 0]
RADIUS = 0.015
SPACING = RADIUS / 2
DT = 0.0025  # seconds per stored frame: WaterDrop's
GRAVITY = np.array([0.0, -9.81 * DT**2])  # per stored frame squared
CONTACT = SPACING  # the floor pushes a block whose lowest row is closer than this
STIFFNESS = 1.0  # per frame squared: a landing takes about pi / sqrt(k) ~ 3 frames
DAMPING = 1.0  # per frame: damping ratio 0.5
SUBSTEPS = 20
COLUMNS, ROWS = 5, 4  # particles per block: 4 rows are 1.5 R tall, within reach of a few message-passing steps
WATER = 5
# The floor height a block rests at: the spring holds its weight, k * (CONTACT - gap) = |g|.
REST_GAP = CONTACT - abs(GRAVITY[1]) / STIFFNESS

KINDS = ("free_fall", "rest", "landing")  # "drop": free fall released at rest


def block(corner: np.ndarray) -> np.ndarray:
    """[COLUMNS * ROWS, 2] particle offsets of one block, its lower-left particle at `corner`."""
    xs, ys = np.meshgrid(np.arange(COLUMNS), np.arange(ROWS), indexing="ij")
    return corner + SPACING * np.stack([xs.ravel(), ys.ravel()], axis=1)


def simulate_block(bottom: float, velocity: np.ndarray, frames: int) -> np.ndarray:
    """[frames, 2] the displacement of a rigid block's lowest row from its start, and its bottom height
    `bottom` (above the floor); semi-implicit Euler in SUBSTEPS per frame."""
    h = 1.0 / SUBSTEPS
    y, v = bottom, np.asarray(velocity, dtype=float).copy()
    offset = np.zeros(2)
    out = [offset.copy()]
    for _ in range(frames - 1):
        for _ in range(SUBSTEPS):
            push = STIFFNESS * max(CONTACT - y, 0.0) - (DAMPING * v[1] if y < CONTACT else 0.0)
            v = v + (GRAVITY + np.array([0.0, push])) * h
            dy = v * h
            y += dy[1]
            offset = offset + dy
        out.append(offset.copy())
    return np.array(out)


def free_fall(start: np.ndarray, velocity: np.ndarray, frames: int) -> np.ndarray:
    """[frames, 2] a free-falling block's displacement, the closed form of dt = 1 semi-implicit Euler:
    v_t = v_0 + t g, p_t = p_0 + t v_0 + t (t + 1) / 2 g (so p_{t+1} - 2 p_t + p_{t-1} = g exactly)."""
    t = np.arange(frames, dtype=float)[:, None]
    return start + t * velocity + 0.5 * t * (t + 1) * GRAVITY


def draw_block(rng: np.random.Generator, kind: str, x: float, frames: int) -> np.ndarray:
    """[frames, COLUMNS * ROWS, 2] positions of one block of `kind` whose left column is at `x`."""
    shape = block(np.zeros(2))
    if kind in ("free_fall", "drop"):
        # High enough not to reach the floor within the trajectory, starting up or down at up to 0.4 m/s
        # (free fall), or released at rest (drop).
        velocity = (np.array([rng.uniform(-4e-4, 4e-4), rng.uniform(-1e-3, 1e-3)]) if kind == "free_fall"
                    else np.zeros(2))
        drop = max(0.0, -velocity[1]) * frames + 0.5 * abs(GRAVITY[1]) * frames * (frames + 1)
        bottom = rng.uniform(FLOOR + drop + 3 * RADIUS, BOUNDS[1, 1] - ROWS * SPACING - RADIUS)
        path = free_fall(np.array([x, bottom]), velocity, frames)
    else:
        if kind == "rest":
            height, velocity = REST_GAP, np.zeros(2)
        elif kind == "landing":  # lands within the first half of the trajectory
            height = rng.uniform(2 * RADIUS, 6 * RADIUS)
            velocity = np.array([0.0, rng.uniform(-2e-3, 0.0)])
        else:
            raise ValueError(f"unknown block kind {kind!r}; expected one of {KINDS}")
        path = np.array([x, FLOOR + height]) + simulate_block(height, velocity, frames)
    return path[:, None, :] + shape[None]


def trajectory(rng: np.random.Generator, kinds: list[str], frames: int) -> Trajectory:
    """One trajectory with a block of each kind in `kinds`, side by side (5 R between blocks)."""
    width = (COLUMNS - 1) * SPACING
    gap = 5 * RADIUS
    start = BOUNDS[0, 0] + 2 * RADIUS
    blocks = [draw_block(rng, kind, start + i * (width + gap), frames) for i, kind in enumerate(kinds)]
    position = np.concatenate(blocks, axis=1).astype(np.float32)
    return Trajectory(position, np.full(position.shape[1], WATER, dtype=np.int64))


def mixed_split(rng: np.random.Generator, count: int, frames: int, blocks: int = 4,
                kinds: tuple[str, ...] = KINDS) -> list[Trajectory]:
    """`count` trajectories of `blocks` blocks each, of `kinds` drawn uniformly."""
    return [trajectory(rng, list(rng.choice(kinds, size=blocks)), frames) for _ in range(count)]


def write(out: Path, train: list[Trajectory], valid: list[Trajectory], test: list[Trajectory],
          **stat_changes: list[float]) -> Path:
    """A dataset in gns-bench's format, statistics from `train` (as `gns-bench generate` computes them),
    any of them replaced by `stat_changes` (a broken pipeline)."""
    stats = {**compute_statistics(train), **stat_changes}
    meta = Metadata(bounds=BOUNDS.tolist(), sequence_length=train[0].num_steps - 1,
                    default_connectivity_radius=RADIUS, dim=2, dt=DT, **stats, name="blocks",
                    particle_types={"water": WATER}, walls=True, gravity=GRAVITY.tolist(),
                    generator={"name": "tests/learning/scenes.py"})
    return write_dataset(out, meta, {"train": train, "valid": valid, "test": test})
