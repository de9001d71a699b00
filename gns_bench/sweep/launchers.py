"""Dispatch sweep runs: several at once on this machine (`Lanes`: worker processes each on its own share of
the cores; `run_parallel` puts a sweep's runs through them), or through submitit (SLURM job arrays on a
cluster, its local executor on one machine).

A sweep's datasets are generated before dispatch (once, by the submitting process; a campaign in lanes makes
them in a lane, `campaign.py`); each job calls the run function it is given (the runner's `execute_run`, bound
to the data, runs and tracking locations) on one planned run.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import TypeVar

from gns_bench.devices import usable_core_ids
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


def core_slices(cores: list[int], parallel: int) -> list[list[int]]:
    """Divide `cores` between `parallel` jobs: disjoint slices, as even as they go (5 cores, 2 jobs: 3 and 2).
    With fewer cores than jobs each job gets one core, taken in turn, and jobs share cores: say so to the user
    (two 2-thread torch jobs on 2 cores made a training step about 10x slower)."""
    if parallel < 1:
        raise ValueError(f"parallel: expected at least 1 job, got {parallel}")
    if not cores:
        raise ValueError("no cores to divide")
    if len(cores) < parallel:
        return [[cores[i % len(cores)]] for i in range(parallel)]
    size, extra = divmod(len(cores), parallel)
    slices, start = [], 0
    for i in range(parallel):
        end = start + size + (1 if i < extra else 0)
        slices.append(cores[start:end])
        start = end
    return slices


def _pin_worker(slices, pids) -> None:  # noqa: ANN001 - a multiprocessing queue and list
    """A worker's initialiser: take one slice of cores for this process (torch's threads follow its affinity,
    `devices.set_threads`) and say its process id (`Lanes.stop` interrupts it)."""
    cores = slices.get()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, cores)
    pids.append(os.getpid())
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # between jobs: a worker that died here would break the pool
    # A spawned process may have imported torch before this ran (with the parent's main module), its thread
    # pool then sized to every core: size it to this process's share.
    import torch

    torch.set_num_threads(len(cores))


def _interrupt_once(signum: int, frame: object) -> None:
    """A lane's SIGINT: the first stops its job (KeyboardInterrupt: training checkpoints its last step, the
    MLflow run ends KILLED); more, as when Ctrl-C in a terminal reaches the lane and `Lanes.stop` forwards it
    too, are ignored, so that they cannot cut that checkpoint short. Between jobs a lane ignores SIGINT."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise KeyboardInterrupt


def _in_lane(stopping, job: Callable[..., Result], *args: object) -> Result:  # noqa: ANN001 - a manager Event
    """Run `job(*args)` in a lane, unless the lanes are stopping: a process pool hands a worker its next job
    before the last ends, and that job must not begin after a stop."""
    if stopping.is_set():
        raise RuntimeError("not started: the lanes were stopping")
    signal.signal(signal.SIGINT, _interrupt_once)
    try:
        return job(*args)
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


class Lanes:
    """`parallel` worker processes (spawned), each pinned to its own slice of this process's cores for its
    life (`core_slices`); on a GPU they share the device. A job submitted runs in whichever lane is free:
    `with Lanes(2) as lanes: future = lanes.submit(job, run)`. Leaving the block by an exception (Ctrl-C, or
    the SIGTERM `cli.interrupt_on_signals` turns into one) stops the lanes' jobs first (`stop`), so that a
    signal to this process alone ends the runs in its lanes as well, each checkpointed where it was."""

    def __init__(self, parallel: int, echo: Callable[[str], None] = print) -> None:
        cores = usable_core_ids()
        self.parallel = parallel
        self._slices = core_slices(cores, parallel)
        if len(cores) < parallel:
            echo(f"  warning: {parallel} jobs on {len(cores)} cores share them: their step times are not comparable")
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> Lanes:
        context = multiprocessing.get_context("spawn")  # no fork of a process that holds torch threads
        manager = self._stack.enter_context(context.Manager())
        queue = manager.Queue()
        for cores_of_one in self._slices:
            queue.put(cores_of_one)
        self._stopping, self._pids, self._futures = manager.Event(), manager.list(), []
        self._pool = self._stack.enter_context(ProcessPoolExecutor(
            self.parallel, mp_context=context, initializer=_pin_worker, initargs=(queue, self._pids)))
        return self

    def submit(self, job: Callable[..., Result], *args: object) -> Future[Result]:
        future = self._pool.submit(_in_lane, self._stopping, job, *args)
        self._futures = [*(f for f in self._futures if not f.done()), future]
        return future

    def stop(self) -> None:
        """Interrupt the jobs in the lanes (SIGINT: a KeyboardInterrupt in each) and start no queued one.
        The pool's exit then waits for the interrupted jobs (a shutdown here would not)."""
        self._stopping.set()
        for future in self._futures:
            future.cancel()  # the queued ones; a job a worker already holds sees `_stopping`
        for pid in list(self._pids):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGINT)

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if exc_type is not None:
            self.stop()
        self._stack.__exit__(exc_type, *exc)


def run_parallel(job: Callable[[PlannedRun], Result], runs: list[PlannedRun], parallel: int,
                 echo: Callable[[str], None] = print,
                 on_result: Callable[[Result | str], None] | None = None) -> list[Result | str]:
    """`job(run)` for every run, `parallel` at a time, each in its own lane (`Lanes`). Prints each run as it
    ends, with what is still running and waiting, and hands it to `on_result` (in this process). Returns each
    run's result in `runs`' order, or a message saying why its process died outside the run."""
    if not runs:
        return []
    parallel = min(parallel, len(runs))
    results: dict[int, Result | str] = {}
    started = time.perf_counter()
    with Lanes(parallel, echo) as lanes:
        futures = {lanes.submit(job, run): i for i, run in enumerate(runs)}
        for done, future in enumerate(as_completed(futures), 1):
            i = futures[future]
            results[i] = outcome_of(future, runs[i].name)
            if on_result is not None:
                on_result(results[i])
            status = getattr(results[i], "status", "FAILED")
            elapsed = time.perf_counter() - started
            left = len(runs) - done
            eta = f", about {elapsed / done * left / 60:.0f} min left" if left else ""
            echo(f"  [{done}/{len(runs)}] {runs[i].name}: {status} after {elapsed / 60:.1f} min "
                 f"({min(parallel, left)} running, {max(left - parallel, 0)} waiting{eta})")
    return [results[i] for i in range(len(runs))]


def outcome_of(future: Future[Result], name: str) -> Result | str:
    """A finished job's result, or a message saying why the process that ran `name` died outside it."""
    try:
        return future.result()
    except Exception as exc:  # noqa: BLE001 - a process that died outside the run
        return f"process of {name}: {type(exc).__name__}: {exc}"
