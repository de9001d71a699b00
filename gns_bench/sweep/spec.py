"""Sweep specs: one TOML per experiment under `sweeps/`, loaded into typed, validated data.

A sweep names a domain, a base config, a grid of axes (`"section.key" = [values]`) or a list of named
candidates (`[candidates.<name>]`, each a config of its own and optionally its own dataset tier: a study
comparing whole configurations), and optional per-tier changes. Tier budgets shared by every sweep live in
`sweeps/tiers.toml`. A run's config is resolved in this order, later winning:

    paper defaults <- sweep [config] <- tiers.toml[tier].config <- sweep [tiers.<tier>].config
                   <- the run's axis values or candidate config <- train.seed from the tier's seeds

Every problem is a `SweepError` naming the file and the key; every run's resolved config is validated
when the spec loads, so a bad value fails before anything runs.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gns_bench.config import TIERS, Config, ConfigError, config_from_dict, read_toml
from gns_bench.sweep.naming import is_sweep_file, sweep_kind, sweep_name

SWEEPS_DIR = Path(__file__).resolve().parents[2] / "sweeps"
TIERS_FILE = "tiers.toml"
_SWEEP_KEYS = {"description", "domain", "dataset_seed", "config", "grid", "candidates", "tiers", "paper_figure",
               "default"}
_TIER_KEYS = {"dataset_tier", "eval_dataset_tier", "seeds", "default_seeds", "config", "grid", "candidates"}
_CANDIDATE_KEYS = {"config", "dataset_tier", "dataset_domain", "seeds"}
CANDIDATE_AXIS = "candidate"  # the one axis of a sweep of named candidates


class SweepError(ValueError):
    """A bad sweep file; the message names the file and the key."""


@dataclass(frozen=True)
class TierSpec:
    dataset_tier: str
    seeds: tuple[int, ...]
    config: dict[str, dict[str, Any]] = field(default_factory=dict)
    grid: dict[str, tuple[Any, ...]] | None = None  # restricts the sweep's axis values at this tier
    eval_dataset_tier: str | None = None  # evaluate on this tier's dataset (None: the one trained on)
    candidates: tuple[str, ...] | None = None  # restricts the sweep's candidates at this tier
    # Seeds of the sweep's `default` point (an ablation's paper-default value), where the other points take
    # `seeds`: the seed spread there is the band ablation verdicts are judged against.
    default_seeds: tuple[int, ...] | None = None


@dataclass(frozen=True)
class Candidate:
    """One named configuration of a study: its config changes and, optionally, its own training data."""

    config: dict[str, dict[str, Any]]
    dataset_tier: str | None = None  # None: the tier's dataset
    dataset_domain: str | None = None  # a variant of the sweep's domain to train on (datasets/variants/)
    seeds: tuple[int, ...] | None = None  # None: the tier's seeds (more for the best candidates of a study)


@dataclass(frozen=True)
class PlannedRun:
    sweep: str
    tier: str
    name: str
    axes: dict[str, Any]  # this run's axis values
    seed: int
    domain: str
    dataset_tier: str
    dataset_seed: int
    config: Config
    eval_dataset_tier: str | None = None  # None: evaluated on the dataset it trains on
    dataset_domain: str | None = None  # trains on this variant of `domain` (None: the domain's own data)

    @property
    def training_domain(self) -> str:
        return self.dataset_domain or self.domain

    @property
    def evaluated_on(self) -> str:
        """The dataset tier of the split this run is evaluated on (of `domain` itself)."""
        return self.eval_dataset_tier or self.dataset_tier

    @property
    def evaluated_elsewhere(self) -> bool:
        """Whether the run is tested on another dataset than the one it trains on."""
        return self.dataset_domain is not None or self.eval_dataset_tier is not None


@dataclass(frozen=True)
class SweepSpec:
    name: str  # <kind>-<file stem> (sweep/naming.py)
    kind: str  # "domain", "ablation", "stress", "study": the folder it sits in
    path: Path
    description: str
    domain: str
    dataset_seed: int
    config: dict[str, dict[str, Any]]
    grid: dict[str, tuple[Any, ...]]
    tiers: dict[str, TierSpec]
    paper_figure: str = ""
    candidates: dict[str, Candidate] = field(default_factory=dict)
    default: dict[str, Any] = field(default_factory=dict)  # the grid point at the paper's default values

    @property
    def experiment(self) -> str:
        return f"sweep:{self.name}"

    @property
    def axes(self) -> list[str]:
        return [CANDIDATE_AXIS] if self.candidates else list(self.grid)

    def plan(self, tier: str) -> list[PlannedRun]:
        """Every run of the grid at this tier, one per combination of axis values and seed."""
        if tier not in self.tiers:
            raise SweepError(f"{self.path}: unknown tier {tier!r}; expected one of {list(self.tiers)}")
        spec = self.tiers[tier]
        runs = []
        for axes, changes, dataset_tier, dataset_domain in self._points(spec):
            seeds = spec.seeds
            if self.candidates and self.candidates[axes[CANDIDATE_AXIS]].seeds:
                seeds = self.candidates[axes[CANDIDATE_AXIS]].seeds
            if spec.default_seeds and self.default and axes == self.default:
                seeds = spec.default_seeds
            for seed in seeds:
                data = _merge(self.config, spec.config, changes)
                data.setdefault("train", {})["seed"] = seed
                label = ",".join(f"{key.split('.')[-1]}={value}" for key, value in axes.items())
                run_name = f"{label}-seed{seed}" if label else f"seed{seed}"
                try:
                    config = config_from_dict(data, f"{self.path} (tier {tier}, run {run_name})")
                except ConfigError as exc:
                    raise SweepError(str(exc)) from None
                train_tier = dataset_tier or spec.dataset_tier
                evaluated = spec.eval_dataset_tier or train_tier
                runs.append(PlannedRun(self.name, tier, run_name, axes, seed, self.domain, train_tier,
                                       self.dataset_seed, config,
                                       evaluated if evaluated != train_tier or dataset_domain else None,
                                       dataset_domain))
        return runs

    def _points(self, spec: TierSpec
                ) -> list[tuple[dict[str, Any], dict[str, dict[str, Any]], str | None, str | None]]:
        """(axis values, config changes, dataset tier or None, dataset domain or None) of every point of the
        sweep at a tier."""
        if self.candidates:
            names = spec.candidates or tuple(self.candidates)
            return [({CANDIDATE_AXIS: name}, self.candidates[name].config, self.candidates[name].dataset_tier,
                      self.candidates[name].dataset_domain) for name in names]
        grid = dict(self.grid)
        if spec.grid:
            grid.update(spec.grid)
        points = []
        for values in itertools.product(*grid.values()) if grid else [()]:
            axes = dict(zip(grid, values, strict=True))
            changes: dict[str, dict[str, Any]] = {}
            for key, value in axes.items():
                section, name = key.split(".")
                changes.setdefault(section, {})[name] = value
            points.append((axes, changes, None, None))
        return points


def _merge(*layers: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for layer in layers:
        for section, values in layer.items():
            out.setdefault(section, {}).update(values)
    return out


def _config_table(value: Any, path: Path, where: str) -> dict[str, dict[str, Any]]:
    if not isinstance(value, dict) or not all(isinstance(v, dict) for v in value.values()):
        raise SweepError(f"{path}: '{where}' must be a table of sections ([model], [train], [eval])")
    try:
        config_from_dict(value, str(path))  # unknown sections/keys and wrong types fail here
    except ConfigError as exc:
        raise SweepError(f"{path}: in '{where}': {exc}") from None
    return value


def _grid_table(value: Any, path: Path, where: str) -> dict[str, tuple[Any, ...]]:
    if not isinstance(value, dict):
        raise SweepError(f"{path}: '{where}' must be a table of \"section.key\" = [values]")
    grid = {}
    for key, values in value.items():
        if key.count(".") != 1:
            raise SweepError(f"{path}: '{where}.{key}': axis keys are \"section.key\", e.g. "
                             "\"model.message_passing_steps\"")
        if not isinstance(values, list) or not values:
            raise SweepError(f"{path}: '{where}.{key}': expected a non-empty list of values")
        if len(set(map(repr, values))) != len(values):
            raise SweepError(f"{path}: '{where}.{key}': repeated values {values}")
        section, name = key.split(".")
        for v in values:
            try:
                config_from_dict({section: {name: v}}, str(path))
            except ConfigError as exc:
                raise SweepError(f"{path}: '{where}.{key}': {exc}") from None
        grid[key] = tuple(values)
    return grid


def reject_unknown_keys(table: dict, known: set[str], path: Path, where: str = "") -> None:
    """Raise `SweepError` naming the file and the first key of `table` (under `where`) not in `known`."""
    unknown = set(table) - known
    if unknown:
        key = f"{where}.{sorted(unknown)[0]}" if where else sorted(unknown)[0]
        raise SweepError(f"{path}: unknown key '{key}'; known keys: {sorted(known)}")


def _tier_table(value: Any, path: Path, where: str, base: TierSpec | None) -> TierSpec:
    if not isinstance(value, dict):
        raise SweepError(f"{path}: '{where}' must be a table")
    reject_unknown_keys(value, _TIER_KEYS, path, where)
    dataset_tier = value.get("dataset_tier", base.dataset_tier if base else None)
    if dataset_tier not in TIERS:
        raise SweepError(f"{path}: '{where}.dataset_tier': expected one of {list(TIERS)}, got {dataset_tier!r}")
    seeds = value.get("seeds", list(base.seeds) if base else None)
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and s >= 0 for s in seeds):
        raise SweepError(f"{path}: '{where}.seeds': expected a non-empty list of non-negative integers")
    config = _config_table(value.get("config", {}), path, f"{where}.config")
    grid = _grid_table(value["grid"], path, f"{where}.grid") if "grid" in value else None
    eval_dataset_tier = value.get("eval_dataset_tier", base.eval_dataset_tier if base else None)
    if eval_dataset_tier is not None and eval_dataset_tier not in TIERS:
        raise SweepError(f"{path}: '{where}.eval_dataset_tier': expected one of {list(TIERS)}, "
                         f"got {eval_dataset_tier!r}")
    default_seeds = value.get("default_seeds", list(base.default_seeds) if base and base.default_seeds else None)
    if default_seeds is not None and (not isinstance(default_seeds, list) or not default_seeds
                                      or not all(isinstance(x, int) and x >= 0 for x in default_seeds)):
        raise SweepError(f"{path}: '{where}.default_seeds': expected a non-empty list of non-negative integers")
    candidates = value.get("candidates")
    if candidates is not None and (not isinstance(candidates, list) or not candidates
                                   or not all(isinstance(c, str) for c in candidates)):
        raise SweepError(f"{path}: '{where}.candidates': expected a non-empty list of candidate names")
    if base is not None:
        config = _merge(base.config, config)
    return TierSpec(dataset_tier, tuple(seeds), config, grid, eval_dataset_tier,
                    tuple(candidates) if candidates else None, tuple(default_seeds) if default_seeds else None)


def _candidates_table(value: Any, path: Path) -> dict[str, Candidate]:
    if not isinstance(value, dict):
        raise SweepError(f"{path}: 'candidates' must be a table of [candidates.<name>] tables")
    candidates = {}
    for name, table in value.items():
        where = f"candidates.{name}"
        if not isinstance(table, dict):
            raise SweepError(f"{path}: '{where}' must be a table")
        reject_unknown_keys(table, _CANDIDATE_KEYS, path, where)
        dataset_tier = table.get("dataset_tier")
        if dataset_tier is not None and dataset_tier not in TIERS:
            raise SweepError(f"{path}: '{where}.dataset_tier': expected one of {list(TIERS)}, got {dataset_tier!r}")
        dataset_domain = table.get("dataset_domain")
        if dataset_domain is not None and not isinstance(dataset_domain, str):
            raise SweepError(f"{path}: '{where}.dataset_domain': expected a variant id, e.g. \"goop-compact\"")
        seeds = table.get("seeds")
        if seeds is not None and (not isinstance(seeds, list) or not seeds
                                  or not all(isinstance(x, int) and x >= 0 for x in seeds)):
            raise SweepError(f"{path}: '{where}.seeds': expected a non-empty list of non-negative integers")
        candidates[name] = Candidate(_config_table(table.get("config", {}), path, f"{where}.config"), dataset_tier,
                                     dataset_domain, tuple(seeds) if seeds else None)
    return candidates


def load_tier_defaults(sweeps_dir: Path = SWEEPS_DIR) -> dict[str, TierSpec]:
    path = sweeps_dir / TIERS_FILE
    data = read_toml(path, SweepError)
    missing = [t for t in TIERS if t not in data]
    if missing:
        raise SweepError(f"{path}: missing tier(s) {missing}")
    unknown = set(data) - set(TIERS)
    if unknown:
        raise SweepError(f"{path}: unknown tier '{sorted(unknown)[0]}'; expected {list(TIERS)}")
    return {tier: _tier_table(data[tier], path, tier, None) for tier in TIERS}


_LOADED: dict[tuple[str, str, bytes, bytes], SweepSpec] = {}  # load_sweep's, by path and both files' bytes


def load_sweep(path: str | Path, sweeps_dir: Path | None = None) -> SweepSpec:
    """The sweep file at `path`, validated (every run of every tier planned), against the tier defaults of
    `sweeps_dir` (by default the nearest folder above it holding `tiers.toml`). A file loaded before with the same
    bytes, under the same defaults, is not parsed and planned again: the reports read every sweep many times."""
    path = Path(path)
    sweeps_dir = sweeps_dir or _find_sweeps_dir(path)
    try:
        key = (str(path.resolve()), str(sweeps_dir.resolve()), path.read_bytes(),
               (sweeps_dir / TIERS_FILE).read_bytes())
    except OSError:
        key = None  # read_toml says what is missing
    if key in _LOADED:
        return _LOADED[key]
    sweep = _load_sweep(path, sweeps_dir)
    if key is not None:
        _LOADED[key] = sweep
    return sweep


def _load_sweep(path: Path, sweeps_dir: Path) -> SweepSpec:
    defaults = load_tier_defaults(sweeps_dir)
    data = read_toml(path, SweepError)
    reject_unknown_keys(data, _SWEEP_KEYS, path)
    domain = data.get("domain")
    if not isinstance(domain, str) or not domain:
        raise SweepError(f"{path}: 'domain': expected a domain id such as \"goop\" or \"tiny\"")
    dataset_seed = data.get("dataset_seed", 0)
    if not isinstance(dataset_seed, int) or dataset_seed < 0:
        raise SweepError(f"{path}: 'dataset_seed': expected a non-negative integer")
    config = _config_table(data.get("config", {}), path, "config")
    grid = _grid_table(data.get("grid", {}), path, "grid")
    candidates = _candidates_table(data.get("candidates", {}), path)
    if grid and candidates:
        raise SweepError(f"{path}: a sweep has a [grid] of axes or [candidates], not both")
    default = data.get("default", {})
    if not isinstance(default, dict) or set(default) != (set(grid) if default else set()):
        raise SweepError(f"{path}: 'default': expected one value per axis of [grid] ({sorted(grid)}), the point "
                         "at the paper's defaults")
    for axis, value in default.items():
        if not any(repr(value) == repr(v) for v in grid[axis]):
            raise SweepError(f"{path}: 'default.{axis}': {value!r} is not among the axis values {list(grid[axis])}")
    tiers_data = data.get("tiers", {})
    if not isinstance(tiers_data, dict):
        raise SweepError(f"{path}: 'tiers' must be a table")
    unknown_tiers = set(tiers_data) - set(TIERS)
    if unknown_tiers:
        raise SweepError(f"{path}: unknown tier 'tiers.{sorted(unknown_tiers)[0]}'; expected {list(TIERS)}")
    tiers = {t: _tier_table(tiers_data.get(t, {}), path, f"tiers.{t}", defaults[t]) for t in TIERS}
    for tier, spec in tiers.items():
        if spec.grid and set(spec.grid) - set(grid):
            raise SweepError(f"{path}: 'tiers.{tier}.grid' names axes {sorted(set(spec.grid) - set(grid))} "
                             "that the sweep's [grid] does not have")
        if spec.candidates and set(spec.candidates) - set(candidates):
            raise SweepError(f"{path}: 'tiers.{tier}.candidates' names {sorted(set(spec.candidates) - set(candidates))}"
                             ", which the sweep's [candidates] do not have")
    sweep = SweepSpec(sweep_name(path, sweeps_dir), sweep_kind(path, sweeps_dir), path,
                      str(data.get("description", "")), domain, dataset_seed, config, grid, tiers,
                      str(data.get("paper_figure", "")), candidates, default)
    for tier in TIERS:
        sweep.plan(tier)  # resolves and validates every run's config now
    return sweep


def _find_sweeps_dir(path: Path) -> Path:
    for parent in path.resolve().parents:
        if (parent / TIERS_FILE).is_file():
            return parent
    return SWEEPS_DIR


def discover_sweeps(sweeps_dir: Path = SWEEPS_DIR) -> list[Path]:
    """Every sweep file (each becomes a nox session), sorted."""
    return sorted(p for p in sweeps_dir.rglob("*.toml") if is_sweep_file(p, sweeps_dir))
