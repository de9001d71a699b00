"""Generate a whole dataset of one domain (or variant) at one tier: train/valid/test and `metadata.json`.

Each trajectory's randomness comes from its own generator seeded by (domain, seed, split, index), so a
run cut off and resumed (DatasetWriter keeps the complete trajectories of `<out>.partial/`) produces
exactly the files an uninterrupted run would. A variant uses its base domain's id here, so its trajectory
i starts as the base's does. Statistics are computed from the generated train split (a variant without
one: its first non-empty split).

The metadata's `generator` records GENERATOR_VERSION. A complete dataset (or a partial one, `<out>.partial/`)
made by an older version whose solver's data has changed since (SOLVER_DATA_VERSION) is stale: it is moved
aside to `<out>.stale-v<version>` (never deleted) and the dataset is generated afresh.
"""

from __future__ import annotations

import importlib
import json
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gns_bench.data.format import SPLITS, DatasetWriter, Metadata, Trajectory, iter_split
from gns_bench.data.statistics import compute_statistics
from gns_bench.physics.spec import DomainSpec, load_domain_spec
from gns_bench.progress import progress_bar

GENERATOR_NAME = "gns-bench"
# Version of the generated data, stored as the metadata's generator["generator_version"] (missing: 1).
#   1: MPM material seeded on a regular lattice, 2 particles per grid cell per dimension
#   2: MPM material seeded i.i.d. uniform in each block, blob and inflow slab at that lattice's density
GENERATOR_VERSION = 2
# The version in which each solver's data last changed: a dataset made before it is stale. SPH and PBD keep
# their lattices (their rest density is computed on one), so their version-1 data is still current.
SOLVER_DATA_VERSION = {"mpm": 2, "sph": 1, "pbd": 1}
VERSION_FILE = "generator_version"  # in `<out>.partial/`: the version writing it, removed once complete
MAX_ATTEMPTS = 3  # initial conditions drawn per trajectory before a blow-up stops the generation
SOLVER_MODULES = {"mpm": "gns_bench.physics.mpm", "sph": "gns_bench.physics.sph",
                  "pbd": "gns_bench.physics.pbd"}


class GenerationError(RuntimeError):
    """A trajectory could not be generated (the solver failed or returned bad data); nothing was written."""


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("gns-bench")
    except Exception:
        return "0+unknown"


def trajectory_rng(domain: str, seed: int, split: str, index: int, attempt: int = 0) -> np.random.Generator:
    """The generator of one trajectory: independent of how many trajectories were generated before."""
    entropy = [zlib.crc32(domain.encode()), seed, SPLITS.index(split), index]
    if attempt:
        entropy.append(attempt)  # a redraw after a failed simulation (see _simulate_with_redraws)
    return np.random.default_rng(np.random.SeedSequence(entropy))


def _simulate_with_redraws(solver: Any, spec: DomainSpec, tier: str, seed: int, split: str, index: int,
                           where: str, bar: Any) -> Trajectory:
    """Simulate one trajectory; if it blows up, report it and redraw its initial condition.

    A failed simulation is never written. Redraws come from (seed, split, index, attempt), so a rerun or a
    resumed run meets the same failures and makes the same redraws; after MAX_ATTEMPTS failures the whole
    generation stops with every attempt's error. Only simulation failures (RuntimeError, which solvers'
    SimulationError derive from, and bad output) are redrawn; a spec error fails at once.
    """
    tier_spec = spec.tier(tier)
    failures = []
    for attempt in range(MAX_ATTEMPTS):
        rng = trajectory_rng(spec.rng_domain, seed, split, index, attempt)
        try:
            traj = solver.simulate(spec.for_trajectory(split, index), tier, rng)
            check_trajectory(traj, spec, tier_spec.sequence_length, where)
            return traj
        except RuntimeError as exc:  # includes GenerationError from the checks
            failures.append(f"attempt {attempt}: {type(exc).__name__}: {exc}")
            message = f"{where}: simulation failed, not written ({failures[-1]})"
            if attempt + 1 < MAX_ATTEMPTS:
                message += "; redrawing its initial condition"
            (bar.write if bar is not None else print)(message, file=sys.stderr)
        except Exception as exc:
            raise GenerationError(f"{where}: {type(exc).__name__}: {exc}") from exc
    raise GenerationError(f"{where}: {MAX_ATTEMPTS} attempts failed: " + " | ".join(failures))


def check_trajectory(traj: Trajectory, spec: DomainSpec, sequence_length: int, where: str) -> None:
    """What the solver returned must be what the tier asks for, finite, and inside the bounds."""
    pos = traj.position
    expected = (sequence_length + 1, pos.shape[1], spec.dim)
    if pos.ndim != 3 or pos.shape != expected:
        raise GenerationError(f"{where}: position has shape {pos.shape}, expected [T, N, D] = {expected}")
    if traj.particle_type.shape != (pos.shape[1],):
        raise GenerationError(f"{where}: particle_type has shape {traj.particle_type.shape}, "
                              f"expected ({pos.shape[1]},)")
    if not np.all(np.isfinite(pos)):
        raise GenerationError(f"{where}: NaN or inf in positions (the simulation blew up)")
    declared = set(spec.particle_types.values())
    present = set(np.unique(traj.particle_type).tolist())
    if not present <= declared:
        raise GenerationError(f"{where}: particle types {sorted(present - declared)} not declared in "
                              f"{spec.path} particle_types")
    bounds = np.asarray(spec.bounds)
    tol = 0.02 * float(np.max(bounds[:, 1] - bounds[:, 0]))
    if np.any(pos < bounds[:, 0] - tol) or np.any(pos > bounds[:, 1] + tol):
        raise GenerationError(f"{where}: particles left the bounds {bounds.tolist()} (span "
                              f"{pos.min(axis=(0, 1)).tolist()} to {pos.max(axis=(0, 1)).tolist()})")
    if (spec.context is None) != (traj.step_context is None):
        raise GenerationError(f"{where}: step_context must be given exactly when the spec has [context]")
    birth = traj.birth_step
    if birth is not None and (birth.shape != (pos.shape[1],) or birth.min(initial=0) < 0
                              or birth.max(initial=0) > sequence_length):
        raise GenerationError(f"{where}: birth_step must hold one frame in [0, {sequence_length}] per "
                              f"particle, got shape {birth.shape}")


def stale_generator_version(path: str | Path) -> int | None:
    """The generator version of the complete dataset at `path` if this generator made it with a version
    older than its solver's data (SOLVER_DATA_VERSION), else None (current, imported, or `tiny`)."""
    generator = json.loads((Path(path) / "metadata.json").read_text()).get("generator") or {}
    solver = generator.get("solver")
    if generator.get("name") != GENERATOR_NAME or solver not in SOLVER_DATA_VERSION:
        return None
    version = int(generator.get("generator_version", 1))
    return version if version < SOLVER_DATA_VERSION[solver] else None


def _partial_version(partial: Path) -> int:
    marker = partial / VERSION_FILE
    return int(marker.read_text()) if marker.is_file() else 1


def set_aside(path: Path, version: int) -> Path:
    """Move a stale dataset (or partial one) to a free sibling `<path>.stale-v<version>[-k]`; say so."""
    aside = path.with_name(f"{path.name}.stale-v{version}")
    k = 1
    while aside.exists():
        k += 1
        aside = path.with_name(f"{path.name}.stale-v{version}-{k}")
    path.rename(aside)
    print(f"{path}: made by generator version {version}, and its solver's data has changed since (now "
          f"version {GENERATOR_VERSION}, see gns_bench/physics/generate.py): stale, moved aside to {aside}; "
          "generating afresh", file=sys.stderr)
    return aside


@dataclass(frozen=True)
class GenerationTiming:
    domain: str
    tier: str
    first_seconds: float  # the first trajectory, the solver's compiling included
    seconds_per_trajectory: float  # the mean of the ones after it
    timed: int
    mean_particles: float
    trajectories: int  # the tier's whole dataset

    @property
    def estimated_minutes(self) -> float:
        return (self.first_seconds + (self.trajectories - 1) * self.seconds_per_trajectory) / 60


def time_generation(domain: str, tier: str, budget_seconds: float = 60.0, seed: int = 0,
                    max_trajectories: int = 12) -> GenerationTiming:
    """Simulate the tier's first training trajectories for about `budget_seconds` (at least three, at most
    `max_trajectories`), writing nothing, and estimate what the whole dataset takes on this machine: how the
    cpu tier's sizes were chosen (at most 15 minutes a domain on 2 cores). Early trajectories
    stand for the rest; GOOP's full small set took 15% longer than this estimate on an AMD EPYC."""
    spec = load_domain_spec(domain).for_tier(tier)
    tier_spec = spec.tier(tier)
    if tier_spec.trajectories["train"] < 1:
        raise ValueError(f"{domain} tier {tier}: no training trajectories to time")
    solver = importlib.import_module(SOLVER_MODULES[spec.solver])
    seconds, particles = [], []
    started = time.perf_counter()
    for index in range(min(max_trajectories, tier_spec.trajectories["train"])):
        if index >= 3 and time.perf_counter() - started > budget_seconds:
            break
        t0 = time.perf_counter()
        traj = solver.simulate(spec.for_trajectory("train", index), tier,
                               trajectory_rng(spec.rng_domain, seed, "train", index))
        seconds.append(time.perf_counter() - t0)
        particles.append(traj.num_particles)
    rest = seconds[1:] or seconds
    return GenerationTiming(domain, tier, seconds[0], float(np.mean(rest)), len(seconds), float(np.mean(particles)),
                            sum(tier_spec.trajectories.values()))


def generate_dataset(domain: str, tier: str, seed: int, out: str | Path, progress: bool = True) -> Path:
    """Generate (or resume, or return unchanged if complete and current) the dataset `out` (where it goes by
    default is gns_bench/datasets.py's `dataset_path`). A stale complete or partial dataset is moved aside
    first (`set_aside`)."""
    spec = load_domain_spec(domain).for_tier(tier)
    tier_spec = spec.tier(tier)
    out = Path(out)
    if (out / "metadata.json").is_file():
        version = stale_generator_version(out)
        if version is None:
            return out
        set_aside(out, version)
    if out.exists():
        raise FileExistsError(f"{out} exists but holds no metadata.json: not a complete dataset; remove it")
    partial = out.with_name(out.name + ".partial")
    if partial.is_dir() and _partial_version(partial) < SOLVER_DATA_VERSION[spec.solver]:
        set_aside(partial, _partial_version(partial))  # never resume it with another generator's data
    solver = importlib.import_module(SOLVER_MODULES[spec.solver])
    writer = DatasetWriter(out)
    (writer.partial_dir / VERSION_FILE).write_text(f"{GENERATOR_VERSION}\n")
    total = sum(tier_spec.trajectories.values())
    done = sum(writer.count(split) for split in SPLITS)
    bar = None
    if progress:
        bar = progress_bar(total=total, initial=done, desc=f"{domain}/{tier}", unit="traj")
    start, particles = time.perf_counter(), []
    for split in SPLITS:
        for index in range(writer.count(split), tier_spec.trajectories[split]):
            where = f"{domain} tier {tier} seed {seed}, {split} trajectory {index}"
            traj = _simulate_with_redraws(solver, spec, tier, seed, split, index, where, bar)
            writer.add(split, traj)
            particles.append(traj.num_particles)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(particles=traj.num_particles)
    if bar is not None:
        bar.close()

    stats_split = next(split for split in SPLITS if tier_spec.trajectories[split])
    stats = compute_statistics(iter_split(writer.partial_dir, stats_split))
    generator = {"name": GENERATOR_NAME, "version": _version(), "generator_version": GENERATOR_VERSION,
                 "domain": domain, "tier": tier, "seed": seed, "solver": spec.solver}
    if spec.base is not None:
        generator.update(base=spec.base, variant=spec.id, statistics_split=stats_split)
    meta = Metadata(
        bounds=spec.bounds, sequence_length=tier_spec.sequence_length,
        default_connectivity_radius=spec.connectivity_radius, dim=spec.dim, dt=spec.dt, **stats,
        name=spec.name, particle_types=dict(spec.particle_types), walls=spec.walls,
        gravity=spec.gravity_per_step2,
        generator=generator,
    )
    path = writer.finish(meta)
    (path / VERSION_FILE).unlink(missing_ok=True)  # the metadata holds it now
    if progress:
        seconds = time.perf_counter() - start
        summary = (f"{domain}/{tier} seed {seed}: {len(particles)} trajectories generated "
                   f"({total - len(particles)} resumed), {tier_spec.sequence_length} steps each")
        if particles:
            summary += f", {min(particles)}-{max(particles)} particles"
        print(f"{summary}, {seconds:.1f} s -> {path}", file=sys.stderr)
    return path
