"""Initial conditions of the MPM domains, drawn from a spec's `[scene]` table.

Keys of `[scene]` (a tier may override any of them in `[tiers.<name>.scene]`):
  blocks            [min, max]   number of material blocks
  block_size        [min, max]   side length of a block, per dimension
  block_materials   [names]      each block's material is drawn from these (particle_types names)
  initial_speed     max          each block gets a velocity uniform in [-max, max] per dimension
  on_floor          bool         blocks rest on the floor (columns) instead of being placed anywhere
  ramps             [min, max]   number of static ramps: thin rectangles at random angles (2D)
  ramp_length, ramp_angle_deg, ramp_thickness
  random_floor      int          number of piecewise-linear floor segments (0: flat container floor)
  floor_height      [min, max]   heights of the floor's vertices above the container bottom
  shake_amplitude   [min, max]   horizontal shaking of the container (fraction of the bounds)
  shake_frequency   [min, max]   in Hz
  container_width   fraction of the bounds' width taken by the shaken container
  fill_height       length       blocks and ramps are placed below this height above the container's
                                 bottom (default: the whole container): a large arena keeps the drop
                                 heights, hence the speeds, of the unit-square domains
  shape             "block" | "blob"   what a block is: a rectangle (default), or a non-convex blob, the
                                 union of `blob_discs` overlapping discs stretched to the block's size,
                                 split by a random line through its centroid between the two
                                 `blob_materials` (the paper's unseen shapes, Sec. 5.2); a blob's solidity
                                 (area / convex hull area) is at most BLOB_MAX_SOLIDITY
  blob_discs        [min, max]   discs per blob (default [3, 5])
  blob_materials    [a, b]       materials of the blob's two sides (one name: the whole blob)
  initial_jitter    length       std of Gaussian noise added to the initial positions of the material
                                 present at frame 0, drawn from a stream of its own (rng.spawn): the scene
                                 is otherwise the one drawn without it (the solver's own sensitivity)
  inflow            [{ position = [x, y], velocity = [vx, vy], width = w, start = f0, stop = f1,
                       material = "water" }, ...]
                                 nozzles emitting streams (2D; gns_bench/physics/inflow.py): round(width
                                 / spacing) particles every spacing / |velocity| seconds, at random in the
                                 slab of stream they fill, from stored frame `start` until frame `stop`.
                                 `blocks` may then be [0, 0]. Emitted particles count towards the tier's
                                 max_particles.
Material is seeded at random, i.i.d. uniform inside each block, blob and stream at one particle per
spacing^D (spacing = half a grid cell: the count of the usual 2-per-cell-per-dimension lattice), from the
trajectory's rng (geometry.random_block, inflow.Emitter.particles).
Obstacles become static grid boundaries in the solver and kinematic particles (type 3) in the data.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gns_bench.physics.geometry import (
    blob_points,
    random_block,
    rectangle,
    sample_boundary,
    union_sdf,
)
from gns_bench.physics.inflow import Emitter, parse_emitters
from gns_bench.physics.spec import DomainSpec, Tier

MAX_PLACEMENT_TRIES = 200
BLOB_MAX_SOLIDITY = 0.85  # a blob covers at most this fraction of its convex hull: clearly non-convex


@dataclass
class MpmScene:
    """Everything the MPM solver needs to start one trajectory."""

    position: np.ndarray  # [N, D] material particles
    velocity: np.ndarray  # [N, D]
    material: np.ndarray  # [N] material model codes (mpm_kernels.WATER, SAND, GOOP)
    particle_type: np.ndarray  # [N] particle type ids of the dataset
    container_lo: np.ndarray  # [D] container walls at rest
    container_hi: np.ndarray
    polygons: list[np.ndarray] = field(default_factory=list)  # static convex obstacles (2D), [V, 2] each
    kinematic: np.ndarray | None = None  # [K, D] boundary particles at rest
    shake: tuple[float, float] | None = None  # (amplitude, angular frequency) of horizontal shaking
    # [N] stored frame at which each particle is emitted (0: present from the start). An inflow particle's
    # `position` and `velocity` are its birth position and the stream's velocity (see `inflow_particles`).
    birth_step: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.birth_step is None:
            self.birth_step = np.zeros(len(self.position), np.int64)

    def offset(self, t: float) -> tuple[float, float]:
        """Horizontal container displacement and velocity at time t (zero unless shaken)."""
        if self.shake is None:
            return 0.0, 0.0
        amp, omega = self.shake
        return amp * math.sin(omega * t), amp * omega * math.cos(omega * t)

    def container(self, t: float) -> tuple[list[float], list[float], list[float]]:
        off, vel = self.offset(t)
        shift = np.zeros_like(self.container_lo)
        shift[0] = off
        velocity = [0.0] * len(shift)
        velocity[0] = vel
        return (self.container_lo + shift).tolist(), (self.container_hi + shift).tolist(), velocity

    def obstacle_sdf(self, grid: int, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance to the obstacles on the grid nodes (negative inside) and its unit gradient.

        `shape`: nodes per dimension, node i at i / grid (mpm.grid_nodes)."""
        dim = self.position.shape[1]
        if not self.polygons:
            return np.full(shape, 1e3, np.float32), np.zeros((*shape, dim), np.float32)
        axes = np.meshgrid(*[np.arange(n) / grid for n in shape], indexing="ij")
        points = np.stack(axes, axis=-1).reshape(-1, dim)
        sdf = union_sdf(points, self.polygons).reshape(shape)
        grad = np.stack(np.gradient(sdf, 1.0 / grid), axis=-1)
        grad /= np.maximum(np.linalg.norm(grad, axis=-1, keepdims=True), 1e-12)
        return sdf, grad

    def kinematic_positions(self, dt: float, frames: int) -> np.ndarray:
        """Boundary particle positions per stored frame, [frames + 1, K, D]."""
        dim = self.position.shape[1]
        if self.kinematic is None or len(self.kinematic) == 0:
            return np.zeros((frames + 1, 0, dim), np.float32)
        out = np.repeat(self.kinematic[None].astype(np.float64), frames + 1, axis=0)
        if self.shake is not None:
            out[:, :, 0] += np.array([self.offset(t * dt)[0] for t in range(frames + 1)])[:, None]
        return out.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Scene building
# ----------------------------------------------------------------------------------------------

def block_scene(material: int, particle_type: int, block_lo: list[float], block_hi: list[float],
                bounds: list[list[float]], grid: int, rng: np.random.Generator) -> MpmScene:
    """One block of one material at rest in a fixed container, seeded at random as the domains' blocks
    are: the setup of the physics tests (water column, dam break, granular collapse)."""
    pts = random_block(np.asarray(block_lo, float), np.asarray(block_hi, float), 0.5 / grid, rng)
    b = np.asarray(bounds, float)
    return MpmScene(pts, np.zeros_like(pts), np.full(len(pts), material), np.full(len(pts), particle_type),
                    b[:, 0].copy(), b[:, 1].copy())


Range = float | tuple[float, float]  # a fixed value, or [min, max] drawn uniformly
SHAPES = ("block", "blob")


@dataclass(frozen=True)
class SceneSpec:
    """An MPM domain's `[scene]` with its tier's `[tiers.<name>.scene]` over it: every key typed, with its
    default here and nowhere else (the module's docstring says what each means). Built and checked once by
    `scene_spec`; `build_scene` only reads it."""

    blocks: tuple[int, int] = (1, 1)
    block_size: Range = (0.1, 0.3)
    block_materials: tuple[str, ...] | None = None  # None: every material of the spec
    initial_speed: float = 0.0
    on_floor: bool = False
    ramps: tuple[int, int] | None = None  # None: no ramps (2D)
    ramp_length: Range = (0.15, 0.3)
    ramp_angle_deg: Range = (-40.0, 40.0)
    ramp_thickness: float = 0.03
    random_floor: int = 0  # floor segments; 0: the container's flat floor
    floor_height: tuple[float, float] = (0.0, 0.2)
    shake_amplitude: Range | None = None  # None: a still container (set with shake_frequency)
    shake_frequency: Range | None = None
    container_width: float = 0.7
    fill_height: float | None = None  # None: the whole container
    shape: str = "block"
    blob_discs: tuple[int, int] = (3, 5)
    blob_materials: tuple[str, ...] | None = None
    initial_jitter: float = 0.0
    inflow: tuple[Emitter, ...] = ()
    inflow_key: str = "scene.inflow"  # where `inflow` was declared, for errors naming it

    @property
    def shaken(self) -> bool:
        return self.shake_amplitude is not None


SCENE_KEYS = frozenset(f.name for f in dataclasses.fields(SceneSpec)) - {"inflow_key"}


def scene_spec(spec: DomainSpec, tier: Tier) -> SceneSpec:
    """The spec's `[scene]` with the tier's overrides, every key checked once (a typo must not be ignored;
    an error names the file and the key)."""
    overrides = tier.params.get("scene", {})
    for where, table in (("scene", spec.scene), (f"tiers.{tier.name}.scene", overrides)):
        unknown = sorted(set(table) - SCENE_KEYS)
        if unknown:
            raise ValueError(f"{spec.path}: key '{where}.{unknown[0]}': unknown scene key; expected some of "
                             f"{sorted(SCENE_KEYS)}")
    s = {**spec.scene, **overrides}

    def where(key: str) -> str:
        return f"{spec.path}: key '{'tiers.' + tier.name + '.scene' if key in overrides else 'scene'}.{key}'"

    def number(key: str, minimum: float = 0.0) -> float:
        value = s[key]
        if isinstance(value, bool) or not isinstance(value, int | float) or value < minimum:
            raise ValueError(f"{where(key)}: expected a number >= {minimum}, got {value!r}")
        return float(value)

    def pair(key: str, kind: type = float) -> tuple:
        value = s[key]
        ok = (isinstance(value, list) and len(value) == 2 and value[0] <= value[1]
              and all(isinstance(v, kind if kind is int else int | float) and not isinstance(v, bool)
                      for v in value))
        if not ok:
            raise ValueError(f"{where(key)}: expected [min, max] with min <= max ({kind.__name__}s), got {value!r}")
        return (kind(value[0]), kind(value[1]))

    def span(key: str) -> Range:
        return number(key, -math.inf) if isinstance(s[key], int | float) and not isinstance(s[key], bool) \
            else pair(key)

    def names(key: str, most: int | None = None) -> tuple[str, ...]:
        value = s[key]
        if not (isinstance(value, list) and 1 <= len(value) <= (most or len(value) or 1)
                and all(n in spec.materials for n in value)):
            raise ValueError(f"{where(key)}: expected {'one or two' if most == 2 else 'one or more'} of the spec's "
                             f"materials {sorted(spec.materials)}, got {value!r}")
        return tuple(value)

    got: dict[str, Any] = {}
    for key in ("blocks", "ramps", "blob_discs"):
        if key in s:
            got[key] = pair(key, int)
            if got[key][0] < (1 if key == "blob_discs" else 0):
                raise ValueError(f"{where(key)}: expected counts >= {1 if key == 'blob_discs' else 0}, got {s[key]!r}")
    for key in ("block_size", "ramp_length", "ramp_angle_deg", "shake_amplitude", "shake_frequency"):
        if key in s:
            got[key] = span(key)
    if "floor_height" in s:
        got["floor_height"] = pair("floor_height")
    for key in ("initial_speed", "ramp_thickness", "container_width", "fill_height", "initial_jitter"):
        if key in s:
            got[key] = number(key)
    if "random_floor" in s:
        if isinstance(s["random_floor"], bool) or not isinstance(s["random_floor"], int) or s["random_floor"] < 0:
            raise ValueError(f"{where('random_floor')}: expected a whole number of segments >= 0, "
                             f"got {s['random_floor']!r}")
        got["random_floor"] = s["random_floor"]
    if "on_floor" in s:
        if not isinstance(s["on_floor"], bool):
            raise ValueError(f"{where('on_floor')}: expected true or false, got {s['on_floor']!r}")
        got["on_floor"] = s["on_floor"]
    if "block_materials" in s:
        got["block_materials"] = names("block_materials")
    if ("shake_amplitude" in s) != ("shake_frequency" in s):
        raise ValueError(f"{where('shake_frequency')}: shaking needs both shake_amplitude and shake_frequency")
    shape = s.get("shape", SceneSpec.shape)
    if shape not in SHAPES:
        raise ValueError(f"{where('shape')}: expected one of {SHAPES}, got {shape!r}")
    got["shape"] = shape
    if shape == "blob":
        if spec.dim != 2 or "blob_materials" not in s:
            raise ValueError(f"{where('blob_materials')}: blobs (2D only) need blob_materials, one or two of "
                             f"the spec's materials {sorted(spec.materials)}, got {s.get('blob_materials')!r}")
        got["blob_materials"] = names("blob_materials", most=2)
    if "inflow" in s:
        key = f"tiers.{tier.name}.scene.inflow" if "inflow" in overrides else "scene.inflow"
        got["inflow"] = tuple(parse_emitters(s["inflow"], str(spec.path), key, spec.materials, spec.dim))
        got["inflow_key"] = key
    return SceneSpec(**got)


def inflow_emitters(spec: DomainSpec, scene: SceneSpec, lo: np.ndarray, hi: np.ndarray,
                    spacing: float) -> list[Emitter]:
    """The scene's `inflow` nozzles, checked to lie inside the container (errors name the file and key)."""
    for i, e in enumerate(scene.inflow):
        e.check_inside(lo, hi, 2 * spacing, spacing, spec.dt, f"{spec.path}: key '{scene.inflow_key}[{i}].position'")
    return list(scene.inflow)


def _uniform(rng: np.random.Generator, pair: Any) -> float:
    lo, hi = (pair, pair) if isinstance(pair, int | float) else pair
    return float(rng.uniform(lo, hi))


def _ramps(s: SceneSpec, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """Static ramps with centres between 15% and 60% of the height [lo, hi] (the fill region)."""
    count = int(rng.integers(s.ramps[0], s.ramps[1] + 1))
    polys = []
    for _ in range(count):
        length = _uniform(rng, s.ramp_length)
        angle = math.radians(_uniform(rng, s.ramp_angle_deg))
        margin = 0.5 * length
        center = np.array([rng.uniform(lo[0] + margin, hi[0] - margin),
                           rng.uniform(lo[1] + 0.15 * (hi[1] - lo[1]), lo[1] + 0.6 * (hi[1] - lo[1]))])
        polys.append(rectangle(center, length, s.ramp_thickness, angle))
    return polys


def _floor(s: SceneSpec, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    segments = s.random_floor
    xs = np.linspace(lo[0] - 0.05, hi[0] + 0.05, segments + 1)
    heights = lo[1] + rng.uniform(*s.floor_height, size=segments + 1)
    bottom = lo[1] - 0.1
    return [np.array([[xs[i], bottom], [xs[i + 1], bottom], [xs[i + 1], heights[i + 1]], [xs[i], heights[i]]])
            for i in range(segments)]


def build_scene(spec: DomainSpec, tier: Tier, models: dict[str, int], rng: np.random.Generator) -> MpmScene:
    """Draw one trajectory's initial condition. Deterministic given `rng`."""
    s = scene_spec(spec, tier)
    dim = spec.dim
    grid = int(tier.params["grid"])
    spacing = 0.5 / grid  # the usual MPM sampling's density: 2 particles per grid cell per dimension
    bounds = np.asarray(spec.bounds, float)
    lo, hi = bounds[:, 0].copy(), bounds[:, 1].copy()
    shake = None
    if s.shaken:
        amp = _uniform(rng, s.shake_amplitude)
        omega = 2 * math.pi * _uniform(rng, s.shake_frequency)
        width = s.container_width * (hi[0] - lo[0])
        # the container's walls sweep +-amp around the middle and must stay in the bounds
        amp = min(amp, 0.5 * (hi[0] - lo[0] - width))
        mid = 0.5 * (lo[0] + hi[0])
        lo[0], hi[0] = mid - width / 2, mid + width / 2
        shake = (amp, omega)
    fill_hi = hi.copy()  # blocks and ramps go below fill_height
    if s.fill_height is not None:
        fill_hi[1] = min(hi[1], lo[1] + s.fill_height)

    emitters = inflow_emitters(spec, s, lo, hi, spacing)
    inflow = [e.particles(spacing, spec.dt, tier.sequence_length, rng) for e in emitters]

    for _ in range(MAX_PLACEMENT_TRIES):
        polygons: list[np.ndarray] = []
        if dim == 2 and s.ramps is not None:
            polygons += _ramps(s, lo, fill_hi, rng)
        if dim == 2 and s.random_floor:
            polygons += _floor(s, lo, hi, rng)
        if not emitters or not polygons or _clear_of(polygons, emitters, spacing, spec.dt):
            break
    else:
        raise RuntimeError(f"{spec.path}: could not place the ramps clear of the inflow nozzles in "
                           f"{MAX_PLACEMENT_TRIES} tries; check [scene] ramps and inflow")

    max_particles = int(tier.params.get("max_particles", 10**9))
    emitted = sum(len(pos) for pos, _ in inflow)
    if emitted > max_particles:
        raise ValueError(f"{spec.path}: key 'tiers.{tier.name}.max_particles': the inflow emits {emitted} "
                         f"particles in {tier.sequence_length} frames, more than max_particles = {max_particles}")
    keep_out = [(r.min(axis=0), r.max(axis=0)) for r in (e.reach(spacing, spec.dt) for e in emitters)]
    for _ in range(MAX_PLACEMENT_TRIES):
        blocks = _place_blocks(s, dim, lo, fill_hi, spacing, polygons, rng, keep_out)
        if blocks is not None and 0 < sum(len(b) for b in blocks) + emitted <= max_particles:
            break
    else:
        raise RuntimeError(f"{spec.path}: could not place blocks with at most {max_particles} particles "
                           f"in {MAX_PLACEMENT_TRIES} tries; check [scene] block_size and the tier's "
                           "max_particles")
    position, velocity, material, ptype = [], [], [], []
    vmax = s.initial_speed

    def add(points: np.ndarray, vel: np.ndarray, name: str) -> None:
        position.append(points)
        velocity.append(np.broadcast_to(vel, points.shape))
        material.append(np.full(len(points), models[name]))
        ptype.append(np.full(len(points), spec.particle_types[name]))

    for block in blocks:
        if s.shape == "blob":
            vel = rng.uniform(-vmax, vmax, size=dim)
            names = s.blob_materials
            angle = rng.uniform(0.0, 2 * math.pi)  # the dividing line, through the blob's centroid
            side = (block - block.mean(axis=0)) @ np.array([math.cos(angle), math.sin(angle)]) >= 0.0
            add(block[side], vel, names[0])
            add(block[~side], vel, names[-1])
        else:
            names = list(s.block_materials or models)
            name = names[int(rng.integers(len(names)))]
            add(block, rng.uniform(-vmax, vmax, size=dim), name)
    birth = [np.zeros(sum(len(p) for p in position), np.int64)]
    for e, (pos, born) in zip(emitters, inflow, strict=True):
        add(pos, e.velocity, e.material)
        birth.append(born)

    kinematic = None
    if polygons:
        kinematic = sample_boundary(polygons, spacing, bounds[:, 0], bounds[:, 1])
    if shake is not None:
        kinematic = _container_walls(lo, hi, spacing)
    scene = MpmScene(np.concatenate(position), np.concatenate(velocity), np.concatenate(material),
                     np.concatenate(ptype), lo, hi, polygons, kinematic, shake, np.concatenate(birth))
    jitter = s.initial_jitter
    if jitter > 0.0:
        # a stream of its own (a child of the trajectory's seed), so the scene above is drawn as without it
        noise = rng.spawn(1)[0]
        present = scene.birth_step == 0
        scene.position[present] += noise.normal(0.0, jitter, size=(int(present.sum()), dim))
    return scene


def _clear_of(polygons: list[np.ndarray], emitters: list[Emitter], spacing: float, dt: float) -> bool:
    """Whether the obstacles keep 4 spacings from every nozzle's reach (its row and pre-birth path)."""
    points = np.concatenate([e.reach(spacing, dt) for e in emitters]
                            + [e.position + e.row_offsets(spacing) for e in emitters])
    return bool(np.min(union_sdf(points, polygons)) >= 4 * spacing)


def _container_walls(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Left, right and bottom walls of a 2D container as particle rows."""
    ys = np.arange(lo[1], hi[1] + 1e-9, spacing)
    xs = np.arange(lo[0] + spacing, hi[0] - spacing / 2, spacing)
    left = np.stack([np.full_like(ys, lo[0]), ys], 1)
    right = np.stack([np.full_like(ys, hi[0]), ys], 1)
    return np.concatenate([left, right, np.stack([xs, np.full_like(xs, lo[1])], 1)])


def _place_blocks(s: SceneSpec, dim: int, lo: np.ndarray, hi: np.ndarray, spacing: float,
                  polygons: list[np.ndarray], rng: np.random.Generator,
                  keep_out: list[tuple[np.ndarray, np.ndarray]] = ()) -> list[np.ndarray] | None:
    """Non-overlapping random boxes (or blobs) of particles, clear of the obstacles and the `keep_out` boxes
    (the inflow nozzles), or None if they do not fit."""
    count = int(rng.integers(s.blocks[0], s.blocks[1] + 1))
    margin = 2 * spacing
    floor_y = lo[1]
    placed: list[tuple[np.ndarray, np.ndarray]] = list(keep_out)
    blocks = []
    for _ in range(count):
        for _ in range(50):
            size = np.array([_uniform(rng, s.block_size) for _ in range(dim)])
            size = np.minimum(size, hi - lo - 2 * margin)
            b_lo = np.array([rng.uniform(lo[d] + margin, hi[d] - margin - size[d]) for d in range(dim)])
            if s.on_floor:
                b_lo[1] = floor_y + spacing / 2
            b_hi = b_lo + size
            if any(np.all(b_lo < p_hi + margin) and np.all(p_lo < b_hi + margin) for p_lo, p_hi in placed):
                continue
            if s.shape == "blob":
                pts, blob_solidity = blob_points(b_lo, b_hi, spacing, list(s.blob_discs), rng)
                if len(pts) < 3 or blob_solidity > BLOB_MAX_SOLIDITY:
                    continue
            else:
                pts = random_block(b_lo, b_hi, spacing, rng)
            near = [p for p in polygons  # only obstacles within reach can be closer than 2 margins
                    if np.all(p.min(axis=0) < b_hi + 2 * margin) and np.all(b_lo - 2 * margin < p.max(axis=0))]
            if near and np.min(union_sdf(pts, near)) < 2 * margin:
                continue
            placed.append((b_lo, b_hi))
            blocks.append(pts)
            break
        else:
            return None
    return blocks
