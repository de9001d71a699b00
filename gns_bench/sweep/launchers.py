"""Dispatch sweep runs through submitit: SLURM job arrays on a cluster, its local executor on one machine.

Datasets are generated before dispatch (once, by the submitting process); each job calls the run
function it is given (the runner's `execute_run`, bound to the data, runs and tracking locations) on one
planned run.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from gns_bench.sweep.spec import PlannedRun

Result = TypeVar("Result")


def submit(job: Callable[[PlannedRun], Result], runs: list[PlannedRun], folder: Path, cluster: str | None = None,
           timeout_min: int = 24 * 60, slurm_partition: str | None = None) -> list[Result | str]:
    """`job(run)` for every run as one job array (cluster None: SLURM when available, else local processes).
    `job` must pickle (a module-level function or a partial of one). Returns each job's result, or a message
    saying why the job died outside the run (e.g. killed by SLURM)."""
    import submitit

    if not runs:
        return []
    executor = submitit.AutoExecutor(folder=str(folder), cluster=cluster)
    parameters = {"timeout_min": timeout_min}
    if executor.cluster == "slurm":
        parameters |= {"slurm_array_parallelism": len(runs)}
        if slurm_partition:
            parameters["slurm_partition"] = slurm_partition
    executor.update_parameters(**parameters)
    jobs = executor.map_array(job, runs)
    results: list[Result | str] = []
    for submitted in jobs:
        try:
            results.append(submitted.result())
        except Exception as exc:  # noqa: BLE001 - a job that died outside the run
            results.append(f"job {submitted.job_id}: {exc}")
    return results
