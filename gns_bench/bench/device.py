"""The checks to run on a lent GPU, from the repository root, in one command:

    python -m gns_bench.bench.device        (or `nox -s device`, where nox is installed)

the CUDA tests (tests/test_cuda.py, skipped on machines without a GPU), training throughput against batch size
eager and replayed from CUDA graphs (gns_bench/bench/graphed.py), the full benchmark on the GPU, and 4
runs of a sweep at once against one at a time, all into the GPU's own folder reports/bench/<machine>/ beside the
CPUs', then the index rewritten. It installs nothing, since such machines may reach no package index. What it
needs beyond the GPU's own CUDA torch and torch-geometric: mlflow (mlflow-skinny with SQLAlchemy and alembic is
enough for the SQLite store) and POT, which the H200 image lacked on 2026-11-30 and were carried there as
wheels. Taichi is not needed: the tests and the benchmark use the tiny domain and synthetic clouds. On an H200
the same steps took 407 s (2026-11-30, wheel installation included, with three of today's five CUDA tests).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import torch

from gns_bench.bench.parallel import measure_parallel, write_parallel_report
from gns_bench.bench.report import BENCH_ROOT, write_bench_index
from gns_bench.bench.run import BenchSettings, bench_dir, run_bench


def run_device_checks(root: Path = BENCH_ROOT, *, parallel: int = 4, steps: int = 300) -> Path:
    """Every check above into `root/<gpu>/`; returns that folder. The tests run first: a failing CUDA path
    stops the check before any timing is written."""
    if not torch.cuda.is_available():
        raise SystemExit("gns_bench.bench.device: torch sees no CUDA device here; these checks are for a GPU")
    out = bench_dir(root, "cuda")
    out.mkdir(parents=True, exist_ok=True)
    # The file, not `-m cuda` over the suite: the other test modules import Taichi and the full mlflow.
    tests = [sys.executable, "-m", "pytest", "tests/test_cuda.py", "-p", "no:cacheprovider", "-q", "-rA",
             f"--junitxml={out / 'cuda-tests.xml'}"]
    if subprocess.run(tests, check=False).returncode != 0:
        raise SystemExit(f"gns_bench.bench.device: CUDA tests failed (see {out / 'cuda-tests.xml'})")
    from gns_bench.bench import graphed  # eager against CUDA graphs over padded buckets, by batch size

    graphed.main(["--out", str(out)])
    run_bench(out, BenchSettings(device="cuda"), log_to_mlflow=False)
    write_parallel_report(measure_parallel(parallel, steps=steps, device="cuda"), out)
    write_bench_index(root)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=BENCH_ROOT, help="benchmark folder (one subfolder a machine)")
    parser.add_argument("--parallel", type=int, default=4, help="runs at once in the parallel timing")
    parser.add_argument("--steps", type=int, default=300, help="training steps a run in the parallel timing")
    args = parser.parse_args(argv)
    print(run_device_checks(args.root, parallel=args.parallel, steps=args.steps) / "README.md")


if __name__ == "__main__":
    main()
