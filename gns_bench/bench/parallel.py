"""What running several sweep runs at once costs: the same runs one at a time and `parallel` at once
(`gns-bench sweep --parallel N`), each way into its own MLflow store and run folders, timed end to end.

On a GPU the paper's graphs fill a fraction of the device, so N runs at once might take little more than one:
on an NVIDIA H200 they did not (4 runs of 300 steps, 48.1 s at once against 45.4 s one after another,
2026-11-30, reports/bench/cuda-nvidia-h200/). On a CPU the cores are divided between them
(`sweep.launchers.core_slices`), so they should take about as long as N one after another. The GPU check
(gns_bench/bench/device.py) runs it on a lent GPU:

    python -m gns_bench.bench.parallel --parallel 4 --device cuda      (into reports/bench/<machine>/)
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from gns_bench import tracking
from gns_bench.bench.report import BENCH_ROOT
from gns_bench.bench.run import bench_dir
from gns_bench.sweep.runner import prepare, run_sweep
from gns_bench.sweep.spec import SWEEPS_DIR, load_sweep

# The paper's processor (M = 10, latent 128) on the tiny domain: one graph of a few hundred particles a step.
SWEEP = '''description = "parallel timing: {runs} seeds of the paper's model on the tiny domain"
domain = "tiny"

[tiers.smoke]
seeds = {seeds}
config.model = {{ latent_size = 128, mlp_hidden_size = 128, message_passing_steps = 10 }}
config.train = {{ steps = {steps}, log_every = {steps}, checkpoint_every = {steps}, device = "{device}" }}
config.eval = {{ max_trajectories = 1, rollout_steps = 10, one_step_windows = 5 }}
'''


def measure_parallel(parallel: int, *, steps: int = 300, device: str = "auto", root: Path | None = None
                     ) -> dict[str, Any]:
    """Seconds for `parallel` runs one at a time and all at once; each way must finish every run."""
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(root or scratch)
        sweeps = root / "sweeps"
        (sweeps / "tests").mkdir(parents=True, exist_ok=True)
        (sweeps / "tiers.toml").write_text((SWEEPS_DIR / "tiers.toml").read_text())
        path = sweeps / "tests" / "parallel.toml"
        path.write_text(SWEEP.format(runs=parallel, seeds=list(range(parallel)), steps=steps, device=device))
        sweep = load_sweep(path, sweeps)
        previous = os.environ.get("MLFLOW_TRACKING_URI")
        seconds: dict[int, float] = {}
        hardware: dict[int, str] = {}
        try:
            tracking.use_tracking_uri(f"sqlite:///{root / 'mlflow-plan.db'}")
            prepare(sweep, "smoke", root / "data", progress=False)  # the dataset made before either timing
            for at_once in (1, parallel):
                tracking.use_tracking_uri(f"sqlite:///{root / f'mlflow-{at_once}.db'}")
                started = time.perf_counter()
                outcomes = run_sweep(sweep, "smoke", data_root=root / "data", runs_root=root / f"runs-{at_once}",
                                     progress=False, share=False, echo=lambda _: None, parallel=at_once)
                seconds[at_once] = time.perf_counter() - started
                failed = [o for o in outcomes if o.status != "FINISHED"]
                if failed:
                    raise RuntimeError(f"{at_once} at a time: {failed[0].name} {failed[0].status}: {failed[0].error}")
                hardware[at_once] = tracking.get_run(outcomes[0].run_id).tags.get("hardware", "?")
        finally:
            if previous is None:
                os.environ.pop("MLFLOW_TRACKING_URI", None)
            else:
                tracking.use_tracking_uri(previous)
    return {"runs": parallel, "steps": steps, "hardware_one_at_a_time": hardware[1],
            "hardware_at_once": hardware[parallel], "seconds_one_at_a_time": seconds[1],
            "seconds_at_once": seconds[parallel], "speedup": seconds[1] / seconds[parallel]}


def write_parallel_report(result: dict[str, Any], out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "parallel.json").write_text(json.dumps(result, indent=2) + "\n")
    path = out_dir / "parallel.md"
    path.write_text(
        f"# {result['runs']} runs at once\n\n"
        f"{result['runs']} runs of the paper's model (M = 10, latent 128) on the tiny domain, {result['steps']} "
        f"training steps and a 10-step evaluation each; wall time end to end, process start and dataset loading "
        f"included. One at a time each run had {result['hardware_one_at_a_time']}; at once, each had "
        f"{result['hardware_at_once']}.\n\n"
        "| one at a time | all at once (`--parallel`) | speed-up |\n|---|---|---|\n"
        f"| {result['seconds_one_at_a_time']:.1f} s | {result['seconds_at_once']:.1f} s | "
        f"{result['speedup']:.2f}x |\n")
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parallel", type=int, default=4, help="runs at once (and in the sequential baseline)")
    parser.add_argument("--steps", type=int, default=300, help="training steps a run")
    parser.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda")
    parser.add_argument("--out", type=Path, default=None, help="where the results go (default: the machine's "
                        "benchmark folder, reports/bench/<machine>/)")
    args = parser.parse_args(argv)
    result = measure_parallel(args.parallel, steps=args.steps, device=args.device)
    print(write_parallel_report(result, args.out or bench_dir(BENCH_ROOT, args.device)).read_text())


if __name__ == "__main__":
    main()
