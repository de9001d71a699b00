"""Run a trained model's stress tests and generalisation rollouts on the scenes they need.

The scenes are dataset variants of the model's training domain (`datasets/variants/`), generated on
first use next to the training data, at the training data's tier unless `stress.dataset_tier` says
otherwise:

    horizon       <domain>-long      the same initial conditions, rolled out 8x longer (without one: the
                                     domain's own test split over its whole length)
    precision     the training domain's own test split
    perturbation  <domain>-jitter    the same initial conditions with jittered positions (solver sensitivity)
    scale         <domain>-x<s>      arenas holding s times the particles
    generalisation: any variant ids, e.g. continuous-heldout, multimaterial-blob, waterramps-inflow

A test whose variant does not exist for the domain is skipped with a note, never silently.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from gns_bench.config import Config
from gns_bench.data.format import Metadata, Trajectory, load_split, read_metadata
from gns_bench.datasets import ensure_dataset
from gns_bench.evaluate.evaluate import Evaluation, evaluate
from gns_bench.evaluate.result import StressResult
from gns_bench.model.simulator import LearnedSimulator
from gns_bench.physics.spec import list_variants, load_domain_spec
from gns_bench.stress import experiments


@dataclass
class StressOutcome:
    results: list[StressResult] = field(default_factory=list)
    generalisation: dict[str, tuple[Evaluation, Metadata]] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)  # what could not run, and why


def _variant_jitter(variant: str) -> float:
    return float(load_domain_spec(variant).scene.get("initial_jitter", 0.0))


def run_stress(simulator: LearnedSimulator, config: Config, dataset_dir: str | Path, *, device: str = "cpu",
               progress: bool = True, echo: Callable[[str], None] = print) -> StressOutcome:
    """Every test and generalisation dataset `config.stress` names, for a simulator trained on `dataset_dir`."""
    stress = config.stress
    dataset_dir = Path(dataset_dir)
    meta = read_metadata(dataset_dir)
    generator = meta.generator or {}
    domain, seed = generator.get("domain", ""), int(generator.get("seed", 0))
    tier = stress.dataset_tier or generator.get("tier", "smoke")
    data_root = dataset_dir.parent
    known = set(list_variants())
    outcome = StressOutcome()
    window = config.model.input_sequence_length

    def scene(variant: str, needed_for: str) -> tuple[list[Trajectory], Metadata] | None:
        if variant not in known:
            outcome.skipped.append(f"{needed_for}: no dataset variant '{variant}' (datasets/variants/{variant}.toml)")
            return None
        path = ensure_dataset(variant, tier, seed, data_root, progress=progress)
        scene_meta = read_metadata(path)
        trajectories = load_split(path, "test", scene_meta, min_length=window + 1)
        return trajectories[: stress.max_trajectories], scene_meta

    base_dir = dataset_dir if tier == generator.get("tier") else ensure_dataset(domain, tier, seed, data_root,
                                                                                 progress=progress)
    base = load_split(base_dir, "test", read_metadata(base_dir), min_length=window + 1)[: stress.max_trajectories]
    steps = stress.rollout_steps
    for test in stress.tests:
        echo(f"stress: {test}")
        if test == "horizon":
            if f"{domain}-long" in known:
                found = scene(f"{domain}-long", "horizon")
                outcome.results.append(experiments.horizon(simulator, found[0], meta.sequence_length, steps=steps,
                                                           device=device))
            else:  # the longest scenes there are: the domain's own test trajectories, whole
                result = experiments.horizon(simulator, base, meta.sequence_length, steps=steps, device=device)
                result.notes.append(f"no variant '{domain}-long': rolled out the test split over its own length")
                outcome.results.append(result)
        elif test == "precision":
            outcome.results.append(experiments.precision(simulator, base, stress.precisions, steps=steps,
                                                         device=device))
        elif test == "perturbation":
            found = scene(f"{domain}-jitter", "perturbation (solver sensitivity)")
            std = stress.perturbation_std or (_variant_jitter(f"{domain}-jitter") if found else 0.0)
            if std <= 0:
                outcome.skipped.append("perturbation: no stress.perturbation_std and no jitter variant to take it from")
                continue
            pairs = list(zip(base, found[0], strict=False)) if found else []
            outcome.results.append(experiments.perturbation(simulator, base, std, solver_pairs=pairs, steps=steps,
                                                            device=device))
        elif test == "scale":
            scenes = {}
            for factor in stress.scales:
                found = scene(f"{domain}-x{factor}", f"scale x{factor}")
                if found:
                    scenes[factor] = (found[0], found[1].bounds)
            if scenes:
                training = sum(t.num_particles for t in base) / len(base)
                outcome.results.append(experiments.scale(simulator, scenes, training, steps=steps, device=device))
    for variant in stress.generalisation:
        echo(f"generalisation: {variant}")
        found = scene(variant, "generalisation")
        if found:
            eval_config = replace(config.eval, max_trajectories=stress.max_trajectories,
                                  rollout_steps=steps if steps is not None else None)
            evaluation = evaluate(simulator, found[0], eval_config, device=device, progress=progress,
                                  bounds=found[1].bounds, gravity=found[1].gravity, walls=found[1].walls)
            outcome.generalisation[variant] = (evaluation, found[1])
    for note in outcome.skipped:
        echo(f"  skipped {note}")
    return outcome
