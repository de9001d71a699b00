"""Domain specifications: one TOML file per domain in `datasets/<id>.toml`, loaded into `DomainSpec`.

A domain is data, not code (STYLE.md): the file says what the paper's domain is (dimension, container,
stored dt, connectivity radius, particle types, the paper's Table 1 figures), how its initial
conditions are randomised (`[scene]`), which materials it holds (`[materials.<name>]`), the solver's own
parameters (a table named after the solver: `[mpm]`, `[sph]`, `[pbd]`, kept raw in `solver_params`) and
three tiers (`[tiers.smoke]`, `[tiers.small]`, `[tiers.paper]`; a tier may set its own `bounds`, e.g. a
CPU-sized arena for a scene whose paper tier is 8.0 x 4.0: `DomainSpec.for_tier`). An optional `[context]`
table declares a global context drawn per trajectory (the friction angle of CONTINUOUS), with held-out
intervals (App. C.5) expressed as `exclude`, or a fixed grid of `values` cycled over the trajectories.

A variant (`datasets/variants/<id>.toml`) is a domain changed for a stress or generalisation test (Sec. 5.3,
App. C.7): `base = "<domain id>"` plus the keys and tables it overrides, deep-merged over the base's file
(tables merge key by key, any other value replaces the base's); its id is its file stem. A variant draws its
trajectories' randomness from its base's stream (`rng_domain`), so its test trajectory i starts from the
base's test trajectory i unless it changes the scene's random draws, and it may set split counts to 0
(an evaluation-only dataset holds only `test`).

Everything is validated here, once; every error in a spec names the file and the key, and an id with no
spec file (`UnknownDomainError`) lists the ids there are.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gns_bench.config import TIERS, read_toml
from gns_bench.data.format import NUM_PARTICLE_TYPES, SPLITS

SOLVERS = ("mpm", "sph", "pbd")
DEFAULT_SPECS_DIR = Path(__file__).resolve().parents[2] / "datasets"
VARIANTS_SUBDIR = "variants"  # datasets/variants/<id>.toml


class SpecError(ValueError):
    """A domain spec is missing, malformed or inconsistent. The message names the file and the key."""

    def __init__(self, path: str | Path, key: str, problem: str):
        super().__init__(f"{path}: key '{key}': {problem}")
        self.path, self.key = str(path), key


class UnknownDomainError(ValueError):
    """No domain or variant has this id. The message names the id and lists every domain and variant."""

    def __init__(self, domain: str, domains: list[str], variants: list[str]):
        super().__init__(f"unknown domain '{domain}'; domains: {', '.join(domains) or 'none'}; "
                         f"variants: {', '.join(variants) or 'none'}")
        self.domain, self.domains, self.variants = domain, list(domains), list(variants)


@dataclass(frozen=True)
class PaperReference:
    """The paper's figures for this domain (Table 1)."""

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

    The exclusion applies to the splits in `exclude_splits` only (App. C.5: train on [0, 80] degrees with
    [30, 55] held out, test over the whole range). With `values` the context is not random: trajectory i
    takes values[i % len(values)] (an evaluation grid, e.g. error against friction angle). The generator
    passes `spec.for_trajectory(split, index)` to the solver, so a solver just calls
    `spec.context.sample(rng)`.
    """

    name: str
    units: str
    low: float
    high: float
    exclude: tuple[tuple[float, float], ...] = ()
    exclude_splits: tuple[str, ...] = ()
    values: tuple[float, ...] = ()  # a fixed grid of values, cycled over the trajectories of a split
    fixed: float | None = None  # set by for_trajectory: this trajectory's value from `values`

    def for_split(self, split: str) -> ContextSpec:
        """The context as drawn for one split: the exclusions apply only to `exclude_splits`."""
        exclude = self.exclude if split in self.exclude_splits else ()
        return dataclasses.replace(self, exclude=exclude, exclude_splits=())

    def for_trajectory(self, split: str, index: int) -> ContextSpec:
        """The context of trajectory `index` of `split`: its grid value when `values` is given."""
        context = self.for_split(split)
        if not self.values:
            return context
        return dataclasses.replace(context, fixed=self.values[index % len(self.values)])

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
        """Uniform over the allowed set: pick an interval with probability proportional to its length.

        A fixed value (from `values`) is returned instead, after the same draws, so that the rest of the
        trajectory (its scene) is drawn exactly as without `values`.
        """
        intervals = self.allowed_intervals()
        lengths = np.array([hi - lo for lo, hi in intervals])
        k = int(rng.choice(len(intervals), p=lengths / lengths.sum()))
        lo, hi = intervals[k]
        value = float(rng.uniform(lo, hi))
        return value if self.fixed is None else float(self.fixed)


@dataclass(frozen=True)
class DomainSpec:
    """One domain, as `datasets/<id>.toml` declares it."""

    id: str
    path: Path
    name: str  # the paper's name, e.g. "WATERDROP"
    description: str
    solver: str  # "mpm" | "sph" | "pbd": picks gns_bench/physics/<solver>.py
    dim: int
    bounds: list[list[float]]  # [[lo, hi]] per dim: the container (a tier may set its own: `for_tier`)
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
    base: str | None = None  # a variant's base domain id (None for a domain)

    @property
    def rng_domain(self) -> str:
        """Whose random stream the trajectories draw from: a variant shares its base's initial conditions."""
        return self.base or self.id

    def tier(self, tier_name: str) -> Tier:
        if tier_name not in self.tiers:
            raise KeyError(f"{self.path}: unknown tier {tier_name!r}; expected one of {sorted(self.tiers)}")
        return self.tiers[tier_name]

    def for_tier(self, tier_name: str) -> DomainSpec:
        """This spec with the tier's own `bounds`, if it sets any (generation and solvers use this)."""
        bounds = self.tier(tier_name).params.get("bounds")
        return self if bounds is None else dataclasses.replace(self, bounds=bounds)

    def for_split(self, split: str) -> DomainSpec:
        """This spec as one split is drawn from (the context's held-out intervals, App. C.5)."""
        if self.context is None:
            return self
        return dataclasses.replace(self, context=self.context.for_split(split))

    def for_trajectory(self, split: str, index: int) -> DomainSpec:
        """This spec as trajectory `index` of `split` is drawn from (a context grid's value, if any)."""
        if self.context is None:
            return self
        return dataclasses.replace(self, context=self.context.for_trajectory(split, index))

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


def _bounds(r: _Reader, name: str, dim: int) -> list[list[float]]:
    bounds = r.get(name, list)
    if (len(bounds) != dim or not all(isinstance(b, list) and len(b) == 2 and b[0] < b[1] for b in bounds)):
        raise r.fail(name, f"expected {dim} pairs [lo, hi] with lo < hi, got {bounds!r}")
    return [[float(lo), float(hi)] for lo, hi in bounds]


def _load_tiers(r: _Reader, *, variant: bool) -> dict[str, Tier]:
    """A domain needs trajectories in every split; a variant may leave splits empty (evaluation only)."""
    tiers_r = r.sub("tiers")
    tiers = {}
    for name in TIERS:
        t = tiers_r.sub(name)
        length = t.positive("sequence_length", int)
        if length < 20 and name != "smoke":
            raise t.fail("sequence_length", f"{length} frames is too short for a '{name}' tier")
        if length < 7:
            raise t.fail("sequence_length", "a training window needs at least 7 frames")
        if variant:
            counts = {split: t.get(split, int) for split in SPLITS}
            for split, count in counts.items():
                if count < 0:
                    raise t.fail(split, f"expected a count >= 0, got {count}")
            if not any(counts.values()):
                raise t.fail("test", "every split is empty; a variant needs trajectories in at least one")
        else:
            counts = {split: t.positive(split, int) for split in SPLITS}
        params = {k: v for k, v in t.table.items() if k not in ("sequence_length", *SPLITS)}
        if "bounds" in params:  # a tier may shrink or grow the arena (e.g. a CPU-sized inflow scene)
            params["bounds"] = _bounds(t, "bounds", len(r.get("bounds", list)))
        tiers[name] = Tier(name, length, counts, params)
    unknown = sorted(set(tiers_r.table) - set(TIERS))
    if unknown:
        raise tiers_r.fail(unknown[0], f"unknown tier; expected {TIERS}")
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
    values = c.get("values", list, [])
    if any(isinstance(v, bool) or not isinstance(v, int | float) or not low <= v <= high for v in values):
        raise c.fail("values", f"expected numbers in the range [{low}, {high}], got {values!r}")
    spec = ContextSpec(c.get("name", str), c.get("units", str, ""), low, high, tuple(exclude), splits,
                       tuple(float(v) for v in values))
    for split in SPLITS:
        if not spec.for_split(split).allowed_intervals():
            raise c.fail("exclude", f"excludes the whole range for split '{split}'")
    return spec


def _check_context_values(c: _Reader, context: ContextSpec, tiers: dict[str, Tier]) -> None:
    """A grid value must not fall in an interval held out of a split that the spec fills."""
    for tier in tiers.values():
        for split in context.exclude_splits:
            if not tier.trajectories[split]:
                continue
            for value in context.values:
                if any(lo < value < hi for lo, hi in context.exclude):
                    raise c.fail("values", f"{value} lies in an interval excluded from split '{split}', "
                                 f"which tier '{tier.name}' fills")


def _read_toml(path: Path) -> dict[str, Any]:
    return read_toml(path, lambda message: SpecError(path, "<file>", message.removeprefix(f"{path}: ")))


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """`override` over `base`: tables merge key by key (recursively), any other value replaces."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _domains_dir_of(path: Path) -> Path:
    """Where a spec file's base domains live: `datasets/` for `datasets/variants/<id>.toml`."""
    return path.parent.parent if path.parent.name == VARIANTS_SUBDIR else path.parent


def load_spec_file(path: str | Path) -> DomainSpec:
    """Load and validate one spec file: a domain, or a variant (resolved over its base domain's file)."""
    path = Path(path)
    raw = _read_toml(path)
    base = None
    if "base" in raw:
        r = _Reader(path, raw)
        base = r.get("base", str)
        if "id" in raw and r.get("id", str) != path.stem:
            raise r.fail("id", f"'{raw['id']}' must match the file name '{path.stem}' (or be left out)")
        base_path = _domains_dir_of(path) / f"{base}.toml"
        if not base_path.is_file():
            known = ", ".join(list_domains(base_path.parent)) or "none"
            raise r.fail("base", f"no domain '{base}' to vary (no {base_path}; known domains: {known})")
        base_raw = _read_toml(base_path)
        if "base" in base_raw:
            raise r.fail("base", f"'{base}' is itself a variant; a variant's base must be a domain")
        raw = deep_merge(base_raw, {k: v for k, v in raw.items() if k != "base"})
        raw["id"] = path.stem
    return _spec_from_raw(path, raw, base)


def _spec_from_raw(path: Path, raw: dict[str, Any], base: str | None) -> DomainSpec:
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
    bounds = _bounds(r, "bounds", dim)

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

    tiers = _load_tiers(r, variant=base is not None)
    context = _load_context(r)
    if context is not None and context.values:
        _check_context_values(r.sub("context"), context, tiers)
    return DomainSpec(
        id=domain_id, path=path, name=r.get("name", str), description=r.get("description", str),
        solver=solver, dim=dim, bounds=bounds, dt=r.positive("dt"),
        connectivity_radius=r.positive("connectivity_radius"), gravity=r.floats("gravity", dim),
        walls=r.get("walls", bool), particle_types=dict(types), paper=paper, tiers=tiers,
        scene=dict(r.get("scene", dict, {})), materials=materials, solver_params=dict(raw[solver]),
        context=context, base=base,
    )


def list_domains(specs_dir: str | Path | None = None) -> list[str]:
    """The ids of every domain with a spec file, sorted (the paper's 16; variants are not domains)."""
    return sorted(p.stem for p in Path(specs_dir or DEFAULT_SPECS_DIR).glob("*.toml"))


def list_variants(specs_dir: str | Path | None = None) -> list[str]:
    """The ids of every variant (`<specs_dir>/variants/<id>.toml`), sorted."""
    return sorted(p.stem for p in (Path(specs_dir or DEFAULT_SPECS_DIR) / VARIANTS_SUBDIR).glob("*.toml"))


def load_domain_spec(domain_id: str, specs_dir: str | Path | None = None) -> DomainSpec:
    """Load `datasets/<domain_id>.toml`, or the variant `datasets/variants/<domain_id>.toml`."""
    specs_dir = Path(specs_dir or DEFAULT_SPECS_DIR)
    path = specs_dir / f"{domain_id}.toml"
    variant_path = specs_dir / VARIANTS_SUBDIR / f"{domain_id}.toml"
    if not path.is_file() and variant_path.is_file():
        path = variant_path
    if not path.is_file():
        raise UnknownDomainError(domain_id, list_domains(specs_dir), list_variants(specs_dir))
    return load_spec_file(path)
