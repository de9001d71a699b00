"""What an evaluation's own switches save: the metric groups it computes (`eval.metrics`) and Verlet lists chosen
by a probe (`eval.neighbour_skin = "auto"`).

Metric groups: each dataset's first test trajectory evaluated with every group, with rollouts alone, and with
one-step errors alone (the tier's one-step windows and rollout length), seconds each; the rollouts' MSE is
compared between the selections (it must not change).

Verlet lists: the probe's timings and choice on that trajectory (`autotune.choose_neighbour_skin`), then the
neighbour finding a rollout does over every true frame of it, with the chosen skin and with none, every
frame's edges from Verlet lists (the chosen skin, or the widest candidate where none was chosen) compared with a
fresh search's (the same edges in the same order, or the row says not), beside the seconds of one
rollout step, so the share the search has of a step shows what the choice can buy.

The model: a checkpoint's (`--checkpoint`, one trained on the dataset), else the paper's model untrained (its
rollouts wander, so monitors only flag them here: a rollout runs whole either way).

    python -m gns_bench.bench.evaluation --out reports/bench/<machine>/ --dataset data/waterdrop-cpu-s0 ...
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from gns_bench import autotune
from gns_bench.bench.measure import allocated_machine, bench_parser, timed, write_results
from gns_bench.config import Config, EvalConfig
from gns_bench.data.format import Trajectory, load_split, read_metadata
from gns_bench.evaluate.evaluate import evaluate, neighbour_finders
from gns_bench.model.simulator import LearnedSimulator
from gns_bench.train.checkpoints import build_simulator, load_checkpoint, load_simulator

SELECTIONS = (("all four", ["one_step", "rollout", "distribution", "diagnostics"]), ("rollout", ["rollout"]),
              ("one-step", ["one_step"]))
# The cpu tier's evaluation (sweeps/tiers.toml), one trajectory, rollouts that no monitor stops.
EVAL = EvalConfig(max_trajectories=1, one_step_windows=50, distribution_steps=10, stop_on=[], neighbour_skin=0.0)


def _model(dataset: Path, checkpoint: Path | None) -> tuple[LearnedSimulator, str]:
    if checkpoint is not None:
        simulator, _, _ = load_simulator(checkpoint)
        return simulator, f"trained {load_checkpoint(checkpoint)['step']:,} steps"
    torch.manual_seed(0)
    return build_simulator(Config(), read_metadata(dataset)).eval(), "untrained"


def selection_rows(name: str, simulator: LearnedSimulator, trajectory: Trajectory, gravity: list[float] | None,
                   model: str) -> list[dict[str, Any]]:
    rows = []
    for label, groups in SELECTIONS:
        started = time.perf_counter()
        evaluation = evaluate(simulator, [trajectory], replace(EVAL, metrics=groups), progress=False,
                              gravity=gravity)
        rows.append({"dataset": name, "model": model, "selection": label, "seconds": time.perf_counter() - started,
                     "rollout_mse": evaluation.metrics.get("rollout_mse", float("nan")),
                     "one_step_mse": evaluation.metrics.get("one_step_mse", float("nan"))})
    return rows


@torch.no_grad()
def skin_row(name: str, simulator: LearnedSimulator, trajectory: Trajectory, model: str,
             repeats: int) -> dict[str, Any]:
    finder, truth = neighbour_finders(simulator, trajectory)
    radius = simulator.radius
    started = time.perf_counter()
    choice = autotune.choose_neighbour_skin(finder, truth, radius)
    probe_seconds = time.perf_counter() - started

    def walk(skin: float) -> list[torch.Tensor]:
        find = finder(skin)
        return [find(position) for position in truth]

    # exactness: the widest candidate skin's lists (or the chosen one) against a fresh search, every frame
    checked = choice.skin or max(autotune.NEIGHBOUR_SKINS) * radius
    same = all(torch.equal(a, b) for a, b in zip(walk(0.0), walk(checked), strict=True))
    fresh = timed(lambda: walk(0.0), repeats, warmup=0) / len(truth)
    chosen = timed(lambda: walk(choice.skin), repeats, warmup=0) / len(truth)
    w = simulator.input_sequence_length
    window = torch.from_numpy(trajectory.position[:w]).transpose(0, 1).contiguous()
    types = torch.from_numpy(trajectory.particle_type)
    step = timed(lambda: simulator.predict_next_position(window, types), repeats)
    return {"dataset": name, "model": model, "particles": trajectory.num_particles, "frames": len(truth),
            "chosen_skin_radii": choice.skin / radius, "probe": choice.describe(), "probe_seconds": probe_seconds,
            "search_fresh_s": fresh, "search_chosen_s": chosen, "speedup": fresh / chosen, "rollout_step_s": step,
            "search_share": fresh / step, "checked_skin_radii": checked / radius, "same_edges": same}


def measure(datasets: tuple[Path, ...], checkpoints: dict[str, Path], repeats: int = 3
            ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    selections, skins = [], []
    for dataset in datasets:
        simulator, model = _model(dataset, checkpoints.get(dataset.name))
        trajectory = load_split(dataset, "test", min_length=simulator.input_sequence_length + 1)[0]
        print(f"{dataset.name}: metric groups...", flush=True)
        selections += selection_rows(dataset.name, simulator, trajectory, read_metadata(dataset).gravity, model)
        print(f"{dataset.name}: Verlet lists...", flush=True)
        skins.append(skin_row(dataset.name, simulator, trajectory, model, repeats))
    return selections, skins


def markdown(selections: list[dict[str, Any]], skins: list[dict[str, Any]], hardware: str) -> str:
    full = {r["dataset"]: r["seconds"] for r in selections if r["selection"] == "all four"}
    lines = [f"Evaluation of one test trajectory by the metric groups it computes (`eval.metrics`; one-step MSE "
             f"over {EVAL.one_step_windows} windows, the whole rollout in fp32, distributional metrics at "
             f"{EVAL.distribution_steps} steps); {hardware}.", "",
             "| dataset | model | metrics | seconds | vs all four | rollout MSE | one-step MSE |",
             "|---|---|---|---|---|---|---|"]
    for r in selections:
        lines.append(f"| {r['dataset']} | {r['model']} | {r['selection']} | {r['seconds']:.1f} | "
                     f"{r['seconds'] / full[r['dataset']]:.2f}x | {r['rollout_mse']:.3g} | {r['one_step_mse']:.3g} |")
    lines += ["", f"Neighbour finding over every true frame of that trajectory with the skin the probe chose "
                  f"(`eval.neighbour_skin = \"auto\"`) and with none, median of repeats, beside one rollout step "
                  f"(fp32); {hardware}.", "",
              "| dataset | particles | frames | probe's choice | probe, s | search a step, ms (none) | "
              "search a step, ms (chosen) | speed-up | rollout step, ms | search's share of a step | same edges, "
              "Verlet lists at |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in skins:
        lines.append(f"| {r['dataset']} | {r['particles']} | {r['frames']} | {r['probe']} | "
                     f"{r['probe_seconds']:.2f} | {1e3 * r['search_fresh_s']:.2f} | {1e3 * r['search_chosen_s']:.2f} | "
                     f"{r['speedup']:.2f}x | {1e3 * r['rollout_step_s']:.1f} | {r['search_share']:.1%} | "
                     f"{'yes' if r['same_edges'] else 'NO'}, {r['checked_skin_radii']:g} R |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, 3)
    parser.add_argument("--dataset", type=Path, nargs="+", required=True)
    parser.add_argument("--checkpoint", type=Path, nargs="*", default=[],
                        help="a checkpoint trained on each dataset, in the same order (none: untrained models)")
    args = parser.parse_args(argv)
    if args.checkpoint and len(args.checkpoint) != len(args.dataset):
        parser.error(f"--checkpoint: one for each of the {len(args.dataset)} datasets, got {len(args.checkpoint)}")
    hardware = allocated_machine(args.allocator)
    checkpoints = {d.name: c for d, c in zip(args.dataset, args.checkpoint, strict=False)}
    selections, skins = measure(tuple(args.dataset), checkpoints, args.repeats)
    text = markdown(selections, skins, hardware)
    write_results(args.out, "evaluation", text, {"selections": selections, "skins": skins})


if __name__ == "__main__":
    main()
