"""The peer at equal budget: geoelements/gns trained through its own training loop against gns-bench's cpu-tier
recipe, on the same data and machine, (a) for the same number of steps and (b) for the same wall time.

The peer runs as it ships (its `train.train`: model, loss, random-walk noise, data loader, Adam and the
release's learning-rate schedule, fp32); it reads the training split exported to its npz layout
(`export_for_geo`) and searches neighbours with gns-bench's search in place of torch-cluster (an edge set: the
same graph, `peer.import_geo`). gns-bench trains with the domain's cpu-tier config, its steps and decay scaled
to the budget. Both are scored by gns-bench's `evaluate` on the same test trajectories, whole rollouts (no
monitor ends one: `stop_on` is empty, so nothing is truncated), the peer through `GeoSimulator`, which puts
its `predict_positions` behind the calls evaluation makes; its rollout loop is the peer's own in effect (true
positions for kinematic particles, the window shifted by one prediction a step).

Each unit (one side, one seed, one budget) writes `<work>/<unit>/score.json` when it is done, so a stopped
study goes on where it stopped. The peer needs `absl-py` (its flags module); it is not a dependency of
gns-bench: `pip install absl-py`.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gns_bench.bench.peer import import_geo
from gns_bench.config import Config, apply_overrides, config_from_dict, resolve_for_dataset
from gns_bench.data.format import Metadata, Trajectory, load_split, read_metadata
from gns_bench.evaluate.evaluate import evaluate

GEO_KEYS = ("bounds", "sequence_length", "dim", "dt", "vel_mean", "vel_std", "acc_mean", "acc_std")
SCORED = ("rollout_mse", "mse_h1", "mse_h10", "mse_h100", "one_step_mse", "gravity_ratio", "rollout_gravity_ratio",
          "com_fall_ratio", "wall_pass_fraction", "rollout_flagged", "rollout_stopped", "rollout_steps")


def export_for_geo(dataset_dir: str | Path, out_dir: str | Path, radius: float) -> Path:
    """The training split of a gns-bench dataset in the peer's layout: `train.npz` (one object array of
    (positions [T, N, D] float32, particle types [N]) per trajectory) and `metadata.json` with the peer's keys,
    its connectivity radius the one gns-bench resolves. Reused when it was exported from the same content."""
    dataset_dir, out_dir = Path(dataset_dir), Path(out_dir)
    meta = read_metadata(dataset_dir)
    marker = out_dir / "exported_from.json"
    source = {"dataset": str(dataset_dir.resolve()), "content_hash": meta.content_hash, "radius": radius}
    if marker.exists() and json.loads(marker.read_text()) == source:
        return out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for index, trajectory in enumerate(load_split(dataset_dir, "train", meta)):
        item = np.empty(2, dtype=object)  # filled one by one: np.array would try to stack equal lengths
        item[0] = trajectory.position.astype(np.float32)
        item[1] = trajectory.particle_type.astype(np.int64)
        arrays[f"trajectory_{index:05d}"] = item
    partial = out_dir / f"train.partial-{os.getpid()}.npz"  # two studies may export at once: same content
    np.savez(partial, **arrays)
    partial.replace(out_dir / "train.npz")
    geo_meta = {key: getattr(meta, key) for key in GEO_KEYS} | {"default_connectivity_radius": radius}
    (out_dir / "metadata.json").write_text(json.dumps(geo_meta, indent=1) + "\n")
    marker.write_text(json.dumps(source) + "\n")
    return out_dir


@dataclass
class GeoTraining:
    model: Path  # the peer's saved weights
    steps: int
    seconds: float  # wall time of its training call, less the time its loader took to read the npz (gns-bench's
    load_seconds: float  # training time leaves the data's loading out too)


def train_geo(geo_source: str | Path, geo_data: Path, out_dir: Path, *, seed: int, noise_std: float,
              steps: int) -> GeoTraining:
    """Train the peer through its own `train.train` for `steps` steps in this process; its per-step prints go to
    `out_dir/geo.log`."""
    import_geo(geo_source)  # patches the neighbour search the training module imports
    import importlib
    geo_train = importlib.import_module("gns.train")
    out_dir.mkdir(parents=True, exist_ok=True)
    flags = {"data_path": f"{geo_data}/", "model_path": f"{out_dir}/", "batch_size": 2, "noise_std": noise_std,
             "ntraining_steps": steps, "validation_interval": None, "nsave_steps": 10**9, "lr_init": 1e-4,
             "lr_decay": 0.1, "lr_decay_steps": int(5e6), "model_file": None, "train_state_file": "train_state.pt"}
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)

    loading = [0.0]
    load = geo_train.data_loader.get_data_loader_by_samples

    def timed_load(*args, **kwargs):
        begun = time.perf_counter()
        try:
            return load(*args, **kwargs)
        finally:
            loading[0] += time.perf_counter() - begun

    geo_train.data_loader.get_data_loader_by_samples = timed_load
    started = time.perf_counter()
    try:
        with open(out_dir / "geo.log", "w") as log, contextlib.redirect_stdout(log):
            geo_train.train(None, flags, 1, torch.device("cpu"))
    finally:
        geo_train.data_loader.get_data_loader_by_samples = load
    elapsed = time.perf_counter() - started
    saved = max(out_dir.glob("model-*.pt"), key=lambda p: int(p.stem.split("-")[1]))
    return GeoTraining(saved, int(saved.stem.split("-")[1]), elapsed - loading[0], loading[0])


class GeoSimulator(torch.nn.Module):
    """A trained peer behind the calls gns-bench's evaluation makes of a simulator: it predicts next positions
    from [N, W, D] windows (fp32 only: the peer runs so), searches its own neighbours each step (no Verlet list
    or static-edge reuse: `uses_edges` False) and has nothing for `eval.compile` to compile (`network` None)."""

    network = None
    uses_edges = False

    def __init__(self, peer: torch.nn.Module, radius: float, bounds: list[list[float]], dim: int,
                 input_sequence_length: int = 6):
        super().__init__()
        self.peer = peer
        self.radius = radius
        self.dim = dim
        self.input_sequence_length = input_sequence_length
        self.register_buffer("bounds", torch.tensor(bounds, dtype=torch.float32))

    @torch.no_grad()
    def predict_next_position(self, window: torch.Tensor, particle_type: torch.Tensor,
                              batch: torch.Tensor | None = None, context: torch.Tensor | None = None,
                              edges: torch.Tensor | None = None, bounds: torch.Tensor | None = None,
                              precision: str = "fp32") -> torch.Tensor:
        if precision != "fp32" or context is not None or bounds is not None:
            raise ValueError("the peer predicts in fp32, without step context or another scene's walls")
        counts = (torch.bincount(batch) if batch is not None
                  else torch.tensor([window.shape[0]], device=window.device))
        return self.peer.predict_positions(window.contiguous(), counts, particle_type)


def load_geo(geo_source: str | Path, geo_data: Path, model: Path, noise_std: float, meta: Metadata,
             radius: float) -> GeoSimulator:
    """A peer model saved by `train_geo`, built as its training built it, behind `GeoSimulator`."""
    import importlib
    import_geo(geo_source)
    geo_train = importlib.import_module("gns.train")
    peer_meta = json.loads((geo_data / "metadata.json").read_text())
    peer = geo_train._get_simulator(peer_meta, noise_std, noise_std, torch.device("cpu"))
    peer.load(str(model))
    peer.eval()
    return GeoSimulator(peer, radius, meta.bounds, meta.dim)


def domain_config(domain: str, sweeps_dir: Path, seed: int, steps: int, seconds: float | None = None) -> Config:
    """The domain's cpu-tier config (its sweep, seed `seed`) with `steps` steps, the learning rate's decay at
    half of them as the tier puts it, and at most `seconds` of training."""
    from gns_bench.sweep.spec import load_sweep

    planned = load_sweep(sweeps_dir / "domains" / f"{domain}.toml").plan("cpu")[0].config
    changes = [f"train.seed={seed}", f"train.steps={steps}", f"train.learning_rate_decay_steps={max(steps // 2, 1)}",
               "train.eval_every=0"]
    if seconds is not None:
        changes.append(f"train.max_wall_seconds={seconds}")
    return config_from_dict(apply_overrides(planned.to_dict(), changes), f"{domain} cpu tier, peer study")


SCORING = 2  # units scored under an earlier rule are scored again (their training is kept)


def score(simulator: torch.nn.Module, trajectories: list[Trajectory], meta: Metadata) -> dict[str, Any]:
    """gns-bench's evaluation in fp32 with its default monitors: a rollout runs to the trajectory's end unless it
    turns non-finite, its energy runs away or its particles collapse onto each other (a collapsed patch also makes
    each step many times dearer: a 500-step model's WATERDROP rollouts took over 10 minutes each). Particles
    through a wall are flagged, not stopped. A stopped rollout is counted as such (`rollout_stopped`, and the
    steps it ran); errors are compared at horizons every rollout reached."""
    from gns_bench.config import EvalConfig

    config = EvalConfig(max_trajectories=len(trajectories), one_step_windows=50, precision="fp32", compile=False)
    evaluation = evaluate(simulator, trajectories, config, progress=False, gravity=meta.gravity, walls=meta.walls)
    rows = [{key: float(row[key]) for key in SCORED if key in row} for row in evaluation.per_trajectory]
    return {"scoring": SCORING, "per_trajectory": rows,
            "mean": {key: float(evaluation.metrics[key]) for key in SCORED if key in evaluation.metrics}}


@dataclass
class Study:
    """Where a study keeps its units, and what it compares on."""

    domain: str
    dataset_dir: Path
    work: Path
    geo_source: Path
    sweeps_dir: Path
    steps: int
    test_trajectories: int

    def unit(self, side: str, seed: int) -> Path:
        return self.work / f"{side}-seed{seed}"

    def test_split(self, meta: Metadata) -> list[Trajectory]:
        return list(load_split(self.dataset_dir, "test", meta))[: self.test_trajectories]


def _read(path: Path) -> dict[str, Any] | None:
    return json.loads(path.read_text()) if path.exists() else None


def _write(path: Path, payload: dict[str, Any]) -> None:
    partial = path.with_suffix(".partial.json")
    partial.write_text(json.dumps(payload, indent=1) + "\n")
    partial.replace(path)


def _trained(unit: Path) -> dict[str, Any] | None:
    """A unit's training record (steps, seconds), also from a score written before training had its own file."""
    found = _read(unit / "trained.json")
    if found is None and (scored := _read(unit / "score.json")) is not None:
        found = {key: scored[key] for key in ("steps", "train_seconds", "load_seconds") if key in scored}
        _write(unit / "trained.json", found)
    return found


def _scored(unit: Path) -> dict[str, Any] | None:
    scored = _read(unit / "score.json")
    return scored if scored is not None and scored.get("scoring") == SCORING else None


def run_seed(study: Study, seed: int, log=print, sides: tuple[str, ...] | None = None) -> None:
    """One seed's units (`sides`, default all): the peer for `steps` steps; gns-bench's cpu-tier recipe for
    `steps` steps, and for the peer's wall time (its steps from its own measured rate, capped by
    `train.max_wall_seconds`); and gns-bench with some of the peer's recipe (`RECIPES`: all of it, which
    separates the implementation from the recipe; with PyTorch's initial weights too; the tier's fp32 or its
    decay alone, which separate the two departures of the tier from the paper). Each unit trains
    once (`trained.json`) and is scored under the current rule (`score.json`); the peer's unit runs first
    whatever `sides` says (the others need its time)."""
    from gns_bench.train.checkpoints import load_simulator
    from gns_bench.train.loop import train

    meta = read_metadata(study.dataset_dir)
    base = resolve_for_dataset(domain_config(study.domain, study.sweeps_dir, seed, study.steps),
                               meta.default_connectivity_radius)
    radius, noise = base.model.connectivity_radius, base.train.noise_std
    tests = study.test_split(meta)
    geo_data = export_for_geo(study.dataset_dir, study.work / "geo-data", radius)

    unit = study.unit("geo-steps", seed)
    if (geo := _trained(unit)) is None:
        log(f"seed {seed}: the peer, {study.steps} steps")
        trained = train_geo(study.geo_source, geo_data, unit, seed=seed, noise_std=noise, steps=study.steps)
        geo = {"steps": trained.steps, "train_seconds": trained.seconds, "load_seconds": trained.load_seconds}
        _write(unit / "trained.json", geo)
    if _scored(unit) is None:
        log(f"seed {seed}: scoring the peer")
        simulator = load_geo(study.geo_source, geo_data, unit / f"model-{geo['steps']}.pt", noise, meta, radius)
        _write(unit / "score.json", {**geo, **score(simulator, tests, meta)})

    def ours(side: str, config: Config) -> dict[str, Any]:
        unit = study.unit(side, seed)
        if (done := _trained(unit)) is None:
            result = train(config, study.dataset_dir, unit, progress=False, resume=(unit / "checkpoint.pt").exists())
            done = {"steps": result.final_step, "train_seconds": result.wall_time_s}
            _write(unit / "trained.json", done)
        if _scored(unit) is None:
            log(f"seed {seed}: scoring {side}")
            simulator, _, _ = load_simulator(unit / "checkpoint.pt")
            _write(unit / "score.json", {**done, **score(simulator, tests, meta)})
        return done

    wanted = set(sides or SIDES)
    if wanted & {"ours-steps", "ours-time"}:
        log(f"seed {seed}: gns-bench, {study.steps} steps")
        same_steps = ours("ours-steps", base)
    if "ours-time" in wanted:
        budget = geo["train_seconds"]
        steps = max(int(study.steps * budget / same_steps["train_seconds"]), 1)
        log(f"seed {seed}: gns-bench for the peer's {budget:.0f} s (about {steps} steps at its rate)")
        ours("ours-time", resolve_for_dataset(domain_config(study.domain, study.sweeps_dir, seed, steps, budget),
                                              meta.default_connectivity_radius))
    for side, changes in RECIPES.items():  # gns-bench with some of the peer's recipe, N steps
        if side in wanted:
            log(f"seed {seed}: {SIDES[side]}")
            ours(side, config_from_dict(apply_overrides(base.to_dict(), changes), SIDES[side]))


SIDES = {"geo-steps": "geoelements/gns, N steps", "ours-steps": "gns-bench, N steps",
         "ours-time": "gns-bench, the peer's wall time",
         "ours-as-peer": "gns-bench as the peer trains (fp32, the paper's decay), N steps",
         "ours-torch-init": "gns-bench as the peer trains, with PyTorch's initial weights, N steps",
         "ours-fp32": "gns-bench, the cpu tier's recipe in fp32, N steps",
         "ours-slow-decay": "gns-bench, the cpu tier's recipe with the paper's decay, N steps"}
# The recipe's changes per side (over the domain's cpu tier): trained as the peer is (fp32, the paper's 5M-step
# decay, which the tier compresses into the run); that with PyTorch's initial weights, the one setting left that
# the peer does differently; and each of the tier's two departures from the paper's recipe alone.
PEER_RECIPE = ["train.precision=fp32", "train.compile=false", "train.learning_rate_decay_steps=5000000"]
RECIPES = {"ours-as-peer": PEER_RECIPE, "ours-torch-init": [*PEER_RECIPE, "model.init=torch"],
           "ours-fp32": PEER_RECIPE[:2], "ours-slow-decay": PEER_RECIPE[2:]}
HORIZONS = ((1, "MSE at rollout step 1"), (10, "MSE over rollout steps 1-10"), (100, "MSE over rollout steps 1-100"))


def collect(work: Path) -> dict[str, dict[int, dict[str, Any]]]:
    """Every unit of a study scored under the current rule: side -> seed -> its score.json."""
    found: dict[str, dict[int, dict[str, Any]]] = {side: {} for side in SIDES}
    for path in sorted(work.glob("*-seed*/score.json")):
        side, seed = path.parent.name.rsplit("-seed", 1)
        if not seed.isdigit():  # a unit set aside (e.g. trained while another job shared its core)
            continue
        scored = json.loads(path.read_text())
        if side in found and scored.get("scoring") == SCORING:
            found[side][int(seed)] = scored
    return found


def _reached(units: list[dict[str, Any]], horizon: int) -> bool:
    """Whether every rollout of every unit ran at least `horizon` steps (the same steps for every model)."""
    return all(row.get("rollout_steps", 0) >= horizon for unit in units for row in unit["per_trajectory"])


def markdown(domain: str, units: dict[str, dict[int, dict[str, Any]]], hardware: str, steps: int,
             test_trajectories: int) -> str:
    """One domain's table: per seed and side the steps, training time, how far its rollouts ran and its errors;
    then each comparison as a ratio of geometric means over seeds with its 95% interval (`report.intervals`), at
    the horizons every rollout of both sides reached."""
    from gns_bench.report.intervals import mean_interval, ratio_interval

    lines = [f"### {domain.upper()}", "",
             f"N = {steps} steps, batch 2; {test_trajectories} test trajectories, rolled out in fp32 with "
             f"gns-bench's default monitors (a rollout stops when non-finite, when its energy runs away or when its "
             f"particles collapse; particles through a wall are flagged, not stopped); {hardware}, one core and one "
             "thread per run.", "",
             "| side | seed | steps | training s | rollouts stopped | steps run (mean) | MSE @1 | MSE 1-10 | "
             "one-step MSE | gravity ratio (one step) | gravity ratio (rollout) | through a wall |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for side, label in SIDES.items():
        for seed, unit in sorted(units[side].items()):
            m = unit["mean"]
            stopped = sum(row.get("rollout_stopped", 0) > 0 for row in unit["per_trajectory"])
            lines.append(f"| {label} | {seed} | {unit['steps']} | {unit['train_seconds']:.0f} | "
                         f"{stopped} of {len(unit['per_trajectory'])} | {m.get('rollout_steps', math.nan):.0f} | "
                         f"{m.get('mse_h1', math.nan):.3g} | {m.get('mse_h10', math.nan):.3g} | "
                         f"{m['one_step_mse']:.3g} | {m['gravity_ratio']:.2f} | {m['rollout_gravity_ratio']:.2f} | "
                         f"{m.get('wall_pass_fraction', math.nan):.0%} |")
    geo = units["geo-steps"]
    compared = [("one_step_mse", "one-step MSE")] + [(f"mse_h{h}", name) for h, name in HORIZONS]
    lines += ["", "| comparison | " + " | ".join(name for _, name in compared) + " |",
              "|---|" + "---|" * len(compared)]
    for side, what in (("ours-steps", "equal steps"), ("ours-time", "equal wall time"),
                       ("ours-as-peer", "equal steps, the peer's recipe"),
                       ("ours-torch-init", "equal steps, the peer's recipe and initialisation"),
                       ("ours-fp32", "equal steps, the cpu tier's recipe in fp32"),
                       ("ours-slow-decay", "equal steps, the cpu tier's recipe with the paper's decay")):
        if not units[side]:
            continue
        both = [*units[side].values(), *geo.values()]
        cells = []
        for key, _ in compared:
            horizon = int(key.removeprefix("mse_h")) if key.startswith("mse_h") else 0
            if horizon and not _reached(both, horizon):
                cells.append("— (a rollout stopped before)")
                continue
            ours = [unit["mean"][key] for unit in units[side].values() if key in unit["mean"]]
            theirs = [unit["mean"][key] for unit in geo.values() if key in unit["mean"]]
            cells.append(ratio_interval(ours, theirs).text(3, "x"))
        lines.append(f"| gns-bench / geoelements/gns, {what} ({len(units[side])} vs {len(geo)} seeds) | "
                     + " | ".join(cells) + " |")
    gravity = {side: mean_interval([u["mean"]["rollout_gravity_ratio"] for u in units[side].values()])
               for side in SIDES if units[side]}
    lines += ["", "Gravity ratio along the rollout (1 = falls at g), mean over seeds with its 95% interval: "
              + "; ".join(f"{SIDES[side]} {interval.text(2)}" for side, interval in gravity.items()) + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description="geoelements/gns and gns-bench at equal steps and equal time")
    parser.add_argument("domain")
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--geo", type=Path, required=True, help="a geoelements/gns checkout (holding gns/)")
    parser.add_argument("--work", type=Path, required=True, help="where units, checkpoints and scores go")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--test-trajectories", type=int, default=3)
    parser.add_argument("--sweeps", type=Path, default=Path("sweeps"))
    parser.add_argument("--sides", nargs="+", choices=list(SIDES), default=None, help="units to run (default all)")
    parser.add_argument("--report", type=Path, default=None,
                        help="train nothing: write the domain's table from --work into REPORT/equal_budget_<domain>.md")
    args = parser.parse_args(argv)
    if args.report is not None:
        from gns_bench.tracking import hardware_description

        text = markdown(args.domain, collect(args.work), hardware_description("cpu"), args.steps,
                        args.test_trajectories)
        args.report.mkdir(parents=True, exist_ok=True)
        (args.report / f"equal_budget_{args.domain}.md").write_text(text)
        (args.report / f"equal_budget_{args.domain}.json").write_text(json.dumps(collect(args.work), indent=1) + "\n")
        print(text)
        return
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", torch.get_num_threads())))
    study = Study(args.domain, args.dataset, args.work, args.geo, args.sweeps, args.steps, args.test_trajectories)
    for seed in args.seeds:
        run_seed(study, seed, log=lambda text: print(text, flush=True), sides=args.sides)


if __name__ == "__main__":
    main()
