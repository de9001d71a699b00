"""Domain specifications: one TOML file per domain in `datasets/<id>.toml`, loaded into `DomainSpec`.

A domain is data, not code (STYLE.md): the file says what the paper's domain is (dimension, container,
stored dt, connectivity radius, particle types, the Knowl 5 reference figures), how its initial
conditions are randomised (`[scene]`), which materials it holds (`[materials.<name>]`), the solver's own
parameters (a table named after the solver: `[mpm]`, `[sph]`, `[pbd]`, kept raw in `solver_params`) and
three tiers (`[tiers.smoke]`, `[tiers.small]`, `[tiers.paper]`). An optional `[context]` table declares a
global context drawn per trajectory (the friction angle of CONTINUOUS), with held-out intervals
(Knowl 7) expressed as `exclude`.

Everything is validated here, once; every error names the file and the key.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gns_bench.data.format import NUM_PARTICLE_TYPES, SPLITS

TIER_NAMES = ("smoke", "small", "paper")
SOLVERS = ("mpm", "sph", "pbd")
DEFAULT_SPECS_DIR = Path(__file__).resolve().parents[2] / "datasets"


class SpecError(ValueError):
    """A domain spec is missing, malformed or inconsistent. The message names the file and the key."""

    def __init__(self, path: str | Path, key: str, problem: str):
        super().__init__(f"{path}: key '{key}': {problem}")
        self.path, self.key = str(path), key


@dataclass(frozen=True)
class PaperReference:
    """The paper's figures for this domain (Knowl 5)."""

    simulator: str
    max_particles: int
    sequence_length: int
    one_step_mse: float  # position MSE, absolute (the table's x1e-9 already applied)
    rollout_mse: float  # position MSE, absolute (the table's x1e-3 already applied)


@dataclass(frozen=True)
class Tier:
    """How much to generate: trajectory counts per split, frames, and solver-specific resolution knobs."""

    name: str
    sequence_length: int  # a trajectory stores sequence_length + 1 frames
    trajectories: dict[str, int]  # split -> count
    params: dict[str, Any] = field(default_factory=dict)  # e.g. {"grid": 64} for MPM


@dataclass(frozen=True)
class ContextSpec:
    """A scalar global context drawn per trajectory, uniform on [low, high] minus `exclude` intervals.

    The exclusion applies to the splits in `exclude_splits` only (Knowl 7: train on [0, 80] degrees with
    [30, 55] held out, test over the whole range). The generator passes `spec.for_split(split)` to the
    solver, so a solver just calls `spec.context.sample(rng)`.
    """

    name: str
    units: str
    low: float
    high: float
    exclude: tuple[tuple[float, float], ...] = ()
    exclude_splits: tuple[str, ...] = ()

    def for_split(self, split: str) -> ContextSpec:
        """The context as drawn for one split: the exclusions apply only to `exclude_splits`."""
        exclude = self.exclude if split in self.exclude_splits else ()
        return dataclasses.replace(self, exclude=exclude, exclude_splits=())

    def allowed_intervals(self) -> list[tuple[float, float]]:
        """[low, high] minus the `exclude` intervals (apply `for_split` first to honour `exclude_splits`)."""
        intervals = [(self.low, self.high)]
        for lo_x, hi_x in self.exclude:
            cut = []
            for lo, hi in intervals:
                if hi_x <= lo or lo_x >= hi:
                    cut.append((lo, hi))
                    continue
                if lo < lo_x:
                    cut.append((lo, lo_x))
                if hi_x < hi:
                    cut.append((hi_x, hi))
            intervals = cut
        return intervals

    def sample(self, rng: np.random.Generator) -> float:
        """Uniform over the allowed set: pick an interval with probability proportional to its length."""
        intervals = self.allowed_intervals()
        lengths = np.array([hi - lo for lo, hi in intervals])
        k = int(rng.choice(len(intervals), p=lengths / lengths.sum()))
        lo, hi = intervals[k]
        return float(rng.uniform(lo, hi))


@dataclass(frozen=True)
class DomainSpec:
    """One domain, as `datasets/<id>.toml` declares it."""

    id: str
    path: Path
    name: str  # the paper's name, e.g. "WATERDROP"
    description: str
    solver: str  # "mpm" | "sph" | "pbd": picks gns_bench/physics/<solver>.py
    dim: int
    bounds: list[list[float]]  # [[lo, hi]] per dim: the container the particles must stay in
    dt: float  # time between stored frames, seconds
    connectivity_radius: float
    gravity: list[float]  # physical gravity vector, per second squared
    walls: bool  # whether the bounds are the container walls (wall-distance features make sense)
    particle_types: dict[str, int]  # name -> id, as in the released data
    paper: PaperReference
    tiers: dict[str, Tier]
    scene: dict[str, Any]  # initial-condition randomisation, interpreted by the solver's scene builder
    materials: dict[str, dict[str, Any]]  # material name -> parameters (name must be in particle_types)
    solver_params: dict[str, Any]  # the raw `[<solver>]` table
    context: ContextSpec | None = None

    def tier(self, tier_name: str) -> Tier:
        if tier_name not in self.tiers:
            raise KeyError(f"{self.path}: unknown tier {tier_name!r}; expected one of {sorted(self.tiers)}")
        return self.tiers[tier_name]

    def for_split(self, split: str) -> DomainSpec:
        """This spec as one split is drawn from (the context's held-out intervals, Knowl 7)."""
        if self.context is None:
            return self
        return dataclasses.replace(self, context=self.context.for_split(split))

    @property
    def gravity_per_step2(self) -> list[float]:
        """Gravity in stored-frame units (g * dt^2), as `metadata.json` stores it."""
        return [g * self.dt**2 for g in self.gravity]


# ----------------------------------------------------------------------------------------------
# Loading and validation
# ----------------------------------------------------------------------------------------------

class _Reader:
    """Typed access to a TOML table; every failure is a SpecError naming file and dotted key."""

    def __init__(self, path: Path, table: dict[str, Any], prefix: str = ""):
        self.path, self.table, self.prefix = path, table, prefix

    def key(self, name: str) -> str:
        return f"{self.prefix}{name}"

    def fail(self, name: str, problem: str) -> SpecError:
        return SpecError(self.path, self.key(name), problem)

    def get(self, name: str, kind: type | tuple[type, ...], default: Any = ..., *, optional: bool = False):
        if name not in self.table:
            if default is not ... or optional:
                return None if default is ... else default
            raise self.fail(name, "missing")
        value = self.table[name]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if isinstance(value, bool) and kind in (int, float):
            raise self.fail(name, f"expected {kind.__name__}, got a boolean")
        if not isinstance(value, kind):
            expected = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
            raise self.fail(name, f"expected {expected}, got {type(value).__name__} {value!r}")
        return value

    def positive(self, name: str, kind: type = float, default: Any = ...):
        value = self.get(name, kind, default)
        if value is not None and not value > 0:
            raise self.fail(name, f"expected a positive number, got {value!r}")
        return value

    def sub(self, name: str, *, optional: bool = False) -> _Reader | None:
        table = self.get(name, dict, optional=optional)
        return None if table is None else _Reader(self.path, table, f"{self.key(name)}.")

    def floats(self, name: str, length: int) -> list[float]:
        value = self.get(name, list)
        if len(value) != length or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                           for v in value):
            raise self.fail(name, f"expected {length} numbers, got {value!r}")
        return [float(v) for v in value]


def _load_tiers(r: _Reader) -> dict[str, Tier]:
    tiers_r = r.sub("tiers")
    tiers = {}
    for name in TIER_NAMES:
        t = tiers_r.sub(name)
        length = t.positive("sequence_length", int)
        if length < 20 and name != "smoke":
            raise t.fail("sequence_length", f"{length} frames is too short for a '{name}' tier")
        if length < 7:
            raise t.fail("sequence_length", "a training window needs at least 7 frames")
        counts = {split: t.positive(split, int) for split in SPLITS}
        params = {k: v for k, v in t.table.items() if k not in ("sequence_length", *SPLITS)}
        tiers[name] = Tier(name, length, counts, params)
    unknown = sorted(set(tiers_r.table) - set(TIER_NAMES))
    if unknown:
        raise tiers_r.fail(unknown[0], f"unknown tier; expected {TIER_NAMES}")
    return tiers


def _load_context(r: _Reader) -> ContextSpec | None:
    c = r.sub("context", optional=True)
    if c is None:
        return None
    low, high = c.floats("range", 2)
    if not low < high:
        raise c.fail("range", f"expected [low, high] with low < high, got {[low, high]}")
    exclude = []
    for i, pair in enumerate(c.get("exclude", list, [])):
        if not (isinstance(pair, list) and len(pair) == 2 and pair[0] < pair[1]):
            raise c.fail(f"exclude[{i}]", f"expected [lo, hi] with lo < hi, got {pair!r}")
        exclude.append((float(pair[0]), float(pair[1])))
    splits = tuple(c.get("exclude_splits", list, []))
    bad = [s for s in splits if s not in SPLITS]
    if bad:
        raise c.fail("exclude_splits", f"unknown split(s) {bad}; expected some of {SPLITS}")
    spec = ContextSpec(c.get("name", str), c.get("units", str, ""), low, high, tuple(exclude), splits)
    for split in SPLITS:
        if not spec.for_split(split).allowed_intervals():
            raise c.fail("exclude", f"excludes the whole range for split '{split}'")
    return spec


def load_spec_file(path: str | Path) -> DomainSpec:
    """Load and validate one spec file."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError as exc:
        raise SpecError(path, "<file>", "no such spec file") from exc
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(path, "<file>", f"invalid TOML: {exc}") from exc
    r = _Reader(path, raw)

    domain_id = r.get("id", str)
    if domain_id != path.stem:
        raise r.fail("id", f"'{domain_id}' must match the file name '{path.stem}'")
    solver = r.get("solver", str)
    if solver not in SOLVERS:
        raise r.fail("solver", f"unknown solver {solver!r}; expected one of {SOLVERS}")
    dim = r.get("dim", int)
    if dim not in (2, 3):
        raise r.fail("dim", f"expected 2 or 3, got {dim}")
    bounds = r.get("bounds", list)
    if (len(bounds) != dim or not all(isinstance(b, list) and len(b) == 2 and b[0] < b[1] for b in bounds)):
        raise r.fail("bounds", f"expected {dim} pairs [lo, hi] with lo < hi, got {bounds!r}")
    bounds = [[float(lo), float(hi)] for lo, hi in bounds]

    types = r.get("particle_types", dict)
    for name, type_id in types.items():
        if not (isinstance(type_id, int) and 0 <= type_id < NUM_PARTICLE_TYPES):
            raise SpecError(path, f"particle_types.{name}", f"expected an id in [0, {NUM_PARTICLE_TYPES})")

    p = r.sub("paper")
    paper = PaperReference(p.get("simulator", str), p.positive("max_particles", int),
                           p.positive("sequence_length", int), p.positive("one_step_mse"),
                           p.positive("rollout_mse"))

    materials_r = r.sub("materials", optional=True)
    materials = {} if materials_r is None else dict(materials_r.table)
    for name, params in materials.items():
        if name not in types:
            raise SpecError(path, f"materials.{name}", f"not among particle_types {sorted(types)}")
        if not isinstance(params, dict):
            raise SpecError(path, f"materials.{name}", "expected a table of parameters")

    if solver not in raw:
        raise r.fail(solver, f"missing: the solver '{solver}' takes its parameters from a [{solver}] table")

    return DomainSpec(
        id=domain_id, path=path, name=r.get("name", str), description=r.get("description", str),
        solver=solver, dim=dim, bounds=bounds, dt=r.positive("dt"),
        connectivity_radius=r.positive("connectivity_radius"), gravity=r.floats("gravity", dim),
        walls=r.get("walls", bool), particle_types=dict(types), paper=paper, tiers=_load_tiers(r),
        scene=dict(r.get("scene", dict, {})), materials=materials, solver_params=dict(raw[solver]),
        context=_load_context(r),
    )


def list_domains(specs_dir: str | Path | None = None) -> list[str]:
    """The ids of every domain with a spec file, sorted."""
    return sorted(p.stem for p in Path(specs_dir or DEFAULT_SPECS_DIR).glob("*.toml"))


def load_domain_spec(domain_id: str, specs_dir: str | Path | None = None) -> DomainSpec:
    """Load `datasets/<domain_id>.toml`."""
    specs_dir = Path(specs_dir or DEFAULT_SPECS_DIR)
    path = specs_dir / f"{domain_id}.toml"
    if not path.is_file():
        known = ", ".join(list_domains(specs_dir)) or "none"
        raise SpecError(path, "<file>", f"no spec for domain '{domain_id}' (known domains: {known})")
    return load_spec_file(path)
