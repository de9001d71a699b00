"""Sweep specs: one TOML per experiment under `sweeps/`, loaded into typed, validated data.

A sweep names a domain, a base config, a grid of axes (`"section.key" = [values]`) and optional
per-tier changes. Tier budgets shared by every sweep live in `sweeps/tiers.toml`. A run's config is
resolved in this order, later winning:

    paper defaults <- sweep [config] <- tiers.toml[tier].config <- sweep [tiers.<tier>].config
                   <- the run's axis values <- train.seed from the tier's seeds

Every problem is a `SweepError` naming the file and the key; every run's resolved config is validated
when the spec loads, so a bad value fails before anything runs.
"""

from __future__ import annotations

import itertools
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gns_bench.config import Config, ConfigError, config_from_dict

TIERS = ("smoke", "small", "paper")
SWEEPS_DIR = Path(__file__).resolve().parents[2] / "sweeps"
TIERS_FILE = "tiers.toml"
# sweeps/<folder>/<file>.toml is named <prefix>-<file>; a folder not listed here loses a final 's' (not 'ss').
# noxfile.py keeps a copy (it runs before gns_bench is installed); a test checks that the two agree.
SWEEP_PREFIXES = {"domains": "domain", "ablations": "ablation", "stress": "stress", "studies": "study"}
_SWEEP_KEYS = {"description", "domain", "dataset_seed", "config", "grid", "tiers", "paper_figure"}
_TIER_KEYS = {"dataset_tier", "seeds", "config", "grid"}


class SweepError(ValueError):
    """A bad sweep file; the message names the file and the key."""


@dataclass(frozen=True)
class TierSpec:
    dataset_tier: str
    seeds: tuple[int, ...]
    config: dict[str, dict[str, Any]] = field(default_factory=dict)
    grid: dict[str, tuple[Any, ...]] | None = None  # restricts the sweep's axis values at this tier


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


@dataclass(frozen=True)
class SweepSpec:
    name: str
    path: Path
    description: str
    domain: str
    dataset_seed: int
    config: dict[str, dict[str, Any]]
    grid: dict[str, tuple[Any, ...]]
    tiers: dict[str, TierSpec]
    paper_figure: str = ""

    @property
    def experiment(self) -> str:
        return f"sweep:{self.name}"

    @property
    def axes(self) -> list[str]:
        return list(self.grid)

    def plan(self, tier: str) -> list[PlannedRun]:
        """Every run of the grid at this tier, one per combination of axis values and seed."""
        if tier not in self.tiers:
            raise SweepError(f"{self.path}: unknown tier {tier!r}; expected one of {list(self.tiers)}")
        spec = self.tiers[tier]
        grid = dict(self.grid)
        if spec.grid:
            grid.update(spec.grid)
        runs = []
        for values in itertools.product(*grid.values()) if grid else [()]:
            axes = dict(zip(grid, values, strict=True))
            for seed in spec.seeds:
                data = _merge(self.config, spec.config)
                for key, value in axes.items():
                    section, name = key.split(".")
                    data.setdefault(section, {})[name] = value
                data.setdefault("train", {})["seed"] = seed
                label = ",".join(f"{key.split('.')[1]}={value}" for key, value in axes.items())
                run_name = f"{label}-seed{seed}" if label else f"seed{seed}"
                try:
                    config = config_from_dict(data, f"{self.path} (tier {tier}, run {run_name})")
                except ConfigError as exc:
                    raise SweepError(str(exc)) from None
                runs.append(PlannedRun(self.name, tier, run_name, axes, seed, self.domain, spec.dataset_tier,
                                       self.dataset_seed, config))
        return runs


def _merge(*layers: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for layer in layers:
        for section, values in layer.items():
            out.setdefault(section, {}).update(values)
    return out


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        return tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise SweepError(f"{path}: no such file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SweepError(f"{path}: invalid TOML ({exc})") from None


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


def _tier_table(value: Any, path: Path, where: str, base: TierSpec | None) -> TierSpec:
    if not isinstance(value, dict):
        raise SweepError(f"{path}: '{where}' must be a table")
    unknown = set(value) - _TIER_KEYS
    if unknown:
        raise SweepError(f"{path}: unknown key '{where}.{sorted(unknown)[0]}'; known keys: {sorted(_TIER_KEYS)}")
    dataset_tier = value.get("dataset_tier", base.dataset_tier if base else None)
    if dataset_tier not in TIERS:
        raise SweepError(f"{path}: '{where}.dataset_tier': expected one of {list(TIERS)}, got {dataset_tier!r}")
    seeds = value.get("seeds", list(base.seeds) if base else None)
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and s >= 0 for s in seeds):
        raise SweepError(f"{path}: '{where}.seeds': expected a non-empty list of non-negative integers")
    config = _config_table(value.get("config", {}), path, f"{where}.config")
    grid = _grid_table(value["grid"], path, f"{where}.grid") if "grid" in value else None
    if base is not None:
        config = _merge(base.config, config)
    return TierSpec(dataset_tier, tuple(seeds), config, grid)


def load_tier_defaults(sweeps_dir: Path = SWEEPS_DIR) -> dict[str, TierSpec]:
    path = sweeps_dir / TIERS_FILE
    data = _read_toml(path)
    missing = [t for t in TIERS if t not in data]
    if missing:
        raise SweepError(f"{path}: missing tier(s) {missing}")
    unknown = set(data) - set(TIERS)
    if unknown:
        raise SweepError(f"{path}: unknown tier '{sorted(unknown)[0]}'; expected {list(TIERS)}")
    return {tier: _tier_table(data[tier], path, tier, None) for tier in TIERS}


def sweep_name(path: Path, sweeps_dir: Path = SWEEPS_DIR) -> str:
    """`sweeps/domains/goop.toml` -> `domain-goop`; `sweeps/ablations/noise_std.toml` -> `ablation-noise_std`;
    `sweeps/studies/learning_rate_decay.toml` -> `study-learning_rate_decay`."""
    try:
        relative = path.resolve().relative_to(sweeps_dir.resolve())
    except ValueError:
        return path.stem
    folder = relative.parts[0] if len(relative.parts) > 1 else ""
    plain = folder[:-1] if folder.endswith("s") and not folder.endswith("ss") else folder  # tests -> test
    prefix = SWEEP_PREFIXES.get(folder, plain)
    return f"{prefix}-{path.stem}" if prefix else path.stem


def load_sweep(path: str | Path, sweeps_dir: Path | None = None) -> SweepSpec:
    path = Path(path)
    sweeps_dir = sweeps_dir or _find_sweeps_dir(path)
    defaults = load_tier_defaults(sweeps_dir)
    data = _read_toml(path)
    unknown = set(data) - _SWEEP_KEYS
    if unknown:
        raise SweepError(f"{path}: unknown key '{sorted(unknown)[0]}'; known keys: {sorted(_SWEEP_KEYS)}")
    domain = data.get("domain")
    if not isinstance(domain, str) or not domain:
        raise SweepError(f"{path}: 'domain': expected a domain id such as \"goop\" or \"tiny\"")
    dataset_seed = data.get("dataset_seed", 0)
    if not isinstance(dataset_seed, int) or dataset_seed < 0:
        raise SweepError(f"{path}: 'dataset_seed': expected a non-negative integer")
    config = _config_table(data.get("config", {}), path, "config")
    grid = _grid_table(data.get("grid", {}), path, "grid")
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
    sweep = SweepSpec(sweep_name(path, sweeps_dir), path, str(data.get("description", "")), domain, dataset_seed,
                      config, grid, tiers, str(data.get("paper_figure", "")))
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
    return sorted(p for p in sweeps_dir.rglob("*.toml") if p.name != TIERS_FILE)
