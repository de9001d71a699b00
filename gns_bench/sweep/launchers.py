"""Dispatch sweep runs through submitit: SLURM job arrays on a cluster, its local executor on one machine.

Datasets are generated before dispatch (once, by the submitting process); each job trains and
evaluates one run and logs to the submitter's tracking store.
"""

from __future__ import annotations

from pathlib import Path

from gns_bench import tracking
from gns_bench.sweep.runner import RunOutcome, execute_run
from gns_bench.sweep.spec import PlannedRun


def _job(run: PlannedRun, data_root: str, runs_root: str, tracking_uri: str) -> RunOutcome:
    return execute_run(run, Path(data_root), Path(runs_root), tracking_uri, progress=False)


def submit(runs: list[PlannedRun], data_root: Path, folder: Path, runs_root: Path, cluster: str | None = None,
           timeout_min: int = 24 * 60, slurm_partition: str | None = None) -> list[RunOutcome]:
    """Run `runs` as one job array; cluster None picks SLURM when available, else local processes."""
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
    uri = tracking.tracking_uri()
    data, root = str(data_root.resolve()), str(runs_root.resolve())
    jobs = executor.map_array(_job, runs, [data] * len(runs), [root] * len(runs), [uri] * len(runs))
    outcomes = []
    for run, job in zip(runs, jobs, strict=True):
        try:
            outcomes.append(job.result())
        except Exception as exc:  # noqa: BLE001 - a job that died outside the run (e.g. killed by SLURM)
            outcomes.append(RunOutcome(run.name, "FAILED", error=f"job {job.job_id}: {exc}"))
    return outcomes
