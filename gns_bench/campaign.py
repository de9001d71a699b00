"""A campaign: sweeps run in priority order by one resumable command, then every report written.

`sweeps/campaigns/<name>.toml` lists sweep files (relative to `sweeps/`) in the order they should fill in
(`sweep/campaigns.py` reads it). `run_campaign` runs what each lacks at a tier (finished runs skipped, those
the committed run summaries under `reports_root` hold included; interrupted ones resumed from their
checkpoints; runs another sweep trained recorded as shared), writes that sweep's report after each run while
others remain and again as soon as it is done (unless it ran nothing new, its run summary holds every run and
its report is newer than the summary) so results land while the rest runs, with the pages that read every sweep
(domain table, stability, baselines, front page: `write_overviews`), and ends by writing every report. A sweep
that fails is reported and the campaign goes on; Ctrl-C or SIGTERM stops it, and the same command resumes it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from gns_bench import tracking
from gns_bench.report import write_all_reports, write_overviews, write_report
from gns_bench.sweep.campaigns import Campaign
from gns_bench.sweep.launchers import Lanes, outcome_of
from gns_bench.sweep.runner import (
    PROGRESS_LOG,
    RunOutcome,
    as_outcome,
    execute_run,
    format_plan,
    prepare,
    ready_branches,
    run_dir,
    run_sweep,
    start_sweep,
    stderr_into,
    waiting_outcome,
)
from gns_bench.sweep.spec import SWEEPS_DIR, PlannedRun, SweepSpec, load_sweep
from gns_bench.sweep.summaries import read_run_summary, summary_path


@dataclass
class SweepResult:
    sweep: str
    outcomes: list[RunOutcome]
    error: str = ""  # the sweep could not run at all (e.g. its dataset failed to generate)


def plan_campaign(campaign: Campaign, tier: str, data_root: Path, echo: Callable[[str], None] = print, *,
                  timed: bool = False, reports_root: Path | None = Path("reports"), runs_root: Path | None = None,
                  any_kind: bool = False) -> None:
    """Print each sweep's runs and their status, generating nothing. `timed`: with each run's step rate
    measured here, its training and evaluation time, and the campaign's total still to run, a point two sweeps
    share counted once (`sweep/timing.py`). `runs_root` and `any_kind` as the campaign itself would run: a
    branch whose checkpoint is not under `runs_root` waits, a run held to another CPU kind waits."""
    if timed:
        from gns_bench.sweep.timing import Total, timed_plan, total_line

        measured: dict[str, object] = {}
        counted: set[str] = set()
        total = Total()
        for path in campaign.sweeps:
            total.add(timed_plan(load_sweep(path), tier, data_root, measured=measured, counted=counted, echo=echo,
                                 reports_root=reports_root))
        echo(f"campaign {campaign.name} ({tier}): " + total_line(total))
        return
    for path in campaign.sweeps:
        sweep = load_sweep(path)
        runs, status, _ = prepare(sweep, tier, data_root, generate=False, reports_root=reports_root,
                                  runs_root=runs_root, any_kind=any_kind)
        echo(format_plan(sweep, tier, runs, status))


def _report_partway(path: Path, tier: str, reports_root: Path, echo: Callable[[str], None],
                    outcome: RunOutcome, runs_left: int) -> None:
    """A run of a sweep with more still to train finished: write the sweep's report now, so its results can be
    read (and committed) while the rest trains. The runner has already put the run into the sweep's summary;
    this costs one report's MLflow reads and pictures, small against a run's 15-55 min. A report that fails
    here is said and left to the sweep's end."""
    if outcome.status != "FINISHED" or runs_left == 0:
        return  # the sweep's end writes the report
    try:
        echo(f"  report so far: {write_report(path, tier, reports_root)}")
    except Exception as exc:  # noqa: BLE001 - a partial report must not stop the runs still to train
        echo(f"  report so far failed ({type(exc).__name__}: {exc}); it is written when {path.stem} is done")


def _write_sweep_reports(path: Path, sweep: SweepSpec, outcomes: list[RunOutcome], tier: str, reports_root: Path,
                         echo: Callable[[str], None]) -> None:
    """A sweep is done: write its report and the overviews, unless nothing ran or was recorded, its summary
    holds every run not waiting for another kind of machine, and its report was written after the summary last
    changed: then the report and the overviews stand as written, and the campaign's final rewrite covers them.
    Rewriting them took about 20 s a sweep (MLflow reads, PNGs): a resumed campaign spent 4.5 min skipping the
    13 sweeps it had done (2-core AMD EPYC, CPU family 25, model 17)."""
    summary = summary_path(reports_root, sweep.name, tier)
    held = read_run_summary(summary)
    readme = summary.parent / "README.md"
    if (all(o.status == "WAITING" or (o.status == "SKIPPED" and o.name in held) for o in outcomes)
            and summary.is_file()
            and readme.is_file() and readme.stat().st_mtime >= summary.stat().st_mtime):
        echo(f"  reports: unchanged, nothing new in {sweep.name}")
        return
    for written in [write_report(path, tier, reports_root), *write_overviews(tier, reports_root)]:
        echo(f"  report: {written}")


def run_campaign(campaign: Campaign, tier: str, *, data_root: Path, runs_root: Path,
                 reports_root: Path = Path("reports"), launcher: str = "local", cluster: str | None = None,
                 progress: bool = True, echo: Callable[[str], None] = print,
                 sweeps_dir: Path = SWEEPS_DIR, parallel: int = 1, any_kind: bool = False) -> list[SweepResult]:
    """Run every sweep of the campaign at `tier` in order, writing each one's report and the overviews when it
    is done, then every report (`write_all_reports`). `parallel` > 1 (local launcher): that many lanes, each a
    process on its own share of the cores, kept busy across sweeps (`_run_in_lanes`): a lane that frees takes
    the next run in the campaign's order, or makes the next sweep's datasets. Runs held to another kind of
    machine wait for a session on one (`sweep/cpu_kinds.py`) while the campaign goes on with the rest, unless
    `any_kind`."""
    if launcher == "local" and parallel > 1:
        results = _run_in_lanes(campaign, tier, data_root=data_root, runs_root=runs_root, reports_root=reports_root,
                                echo=echo, sweeps_dir=sweeps_dir, parallel=parallel, any_kind=any_kind,
                                progress=progress)
        for written in write_all_reports(tier, reports_root, sweeps_dir):
            echo(f"  report: {written}")
        return results
    results = []
    for index, path in enumerate(campaign.sweeps, 1):
        sweep: SweepSpec = load_sweep(path, sweeps_dir)
        echo(f"== campaign {campaign.name} ({tier}), sweep {index}/{len(campaign.sweeps)}: {sweep.name}")
        try:
            outcomes = run_sweep(sweep, tier, data_root=data_root, runs_root=runs_root, launcher=launcher,
                                 cluster=cluster, progress=progress, parallel=parallel, reports_root=reports_root,
                                 echo=echo, after_run=partial(_report_partway, path, tier, reports_root, echo),
                                 any_kind=any_kind)
        except KeyboardInterrupt:
            raise
        except Exception as exc:  # noqa: BLE001 - one sweep's failure (a dataset that would not generate) is reported
            echo(f"  sweep {sweep.name} failed: {type(exc).__name__}: {exc}")
            results.append(SweepResult(sweep.name, [], f"{type(exc).__name__}: {exc}"))
            continue
        results.append(SweepResult(sweep.name, outcomes))
        _write_sweep_reports(path, sweep, outcomes, tier, reports_root, echo)
    for written in write_all_reports(tier, reports_root, sweeps_dir):
        echo(f"  report: {written}")
    return results


@dataclass
class _Started:
    """A sweep of a campaign in lanes whose runs are being trained."""

    index: int
    path: Path
    sweep: SweepSpec
    outcomes: list[RunOutcome]
    keep: Callable[[RunOutcome | str], None]
    left: int  # runs queued or in a lane


def make_datasets(path: Path, tier: str, data_root: Path, sweeps_dir: Path, reports_root: Path,
                  tracking_uri: str | None, log: Path) -> str:
    """A lane's job: generate the datasets a campaign's sweep lacks (`prepare`), its progress into `log`.
    Returns the sweep's name."""
    if tracking_uri:
        tracking.use_tracking_uri(tracking_uri)
    sweep = load_sweep(path, sweeps_dir)
    with stderr_into(log):
        prepare(sweep, tier, data_root, generate=True, progress=True, reports_root=reports_root)
    return sweep.name


HELD_POLL_S = 60.0  # how often a campaign in lanes looks for the checkpoint a held branch starts from


def _run_in_lanes(campaign: Campaign, tier: str, *, data_root: Path, runs_root: Path, reports_root: Path,
                  echo: Callable[[str], None], sweeps_dir: Path, parallel: int, any_kind: bool,
                  progress: bool) -> list[SweepResult]:
    """The campaign's runs through `parallel` lanes (`Lanes`), in the campaign's order across sweeps, so that
    no lane idles while any sweep has a run to train: a free lane takes the next queued run; with none queued,
    the next sweep is started (its finished, shared and waiting runs recorded here, a stress sweep's tests of
    checkpoints another sweep trained run here too, its runs to train queued)
    or, where it lacks a dataset, the lane makes it (one lane at a time: a sweep lacking data while one is made
    waits for it, and the sweeps after it start meanwhile). Each sweep's report is written as its runs finish
    (`_report_partway`) and when its last one has (`_write_sweep_reports`). A run's progress goes to
    `progress.log` in its run directory; a dataset's to `datasets.log` in the sweep's runs folder. A sweep
    whose dataset a lane made starts once it is there, its runs queued ahead of later sweeps'. A branch
    whose checkpoint is not ready (`train.init_from`: a kept checkpoint not yet written, or a run's own
    checkpoint.pt before that run has finished) is held and queued, in the campaign's order, as soon as it is
    (looked at each minute and as each run ends), so a trunk and its branches run in one campaign; its sweep's
    last report waits for it, and what is still held when nothing else is left to run ends WAITING. Ctrl-C, or a
    SIGTERM to this process alone, stops the runs in the lanes too (`Lanes.stop`: each checkpointed, resumable)
    and begins no other."""
    uri = tracking.tracking_uri()
    job = partial(execute_run, data_root=data_root.resolve(), runs_root=runs_root.resolve(), tracking_uri=uri,
                  progress=False, progress_log=progress)
    results: dict[int, SweepResult] = {}
    upcoming = list(enumerate(campaign.sweeps, 1))
    generated: set[int] = set()  # sweeps whose datasets a lane has made (or failed to)
    deferred: list[tuple[int, Path]] = []  # sweeps lacking a dataset while a lane makes another's
    queue: list[tuple[_Started, PlannedRun]] = []
    held: list[tuple[_Started, PlannedRun]] = []  # branches whose checkpoint is not ready yet
    flying: dict[Future, tuple[_Started, PlannedRun] | tuple[int, Path]] = {}
    started_at = time.perf_counter()

    def finish(started: _Started) -> None:
        results[started.index] = SweepResult(started.sweep.name, started.outcomes)
        try:
            _write_sweep_reports(started.path, started.sweep, started.outcomes, tier, reports_root, echo)
        except Exception as exc:  # noqa: BLE001 - a report that fails must not stop the lanes
            echo(f"  reports of {started.sweep.name} failed ({type(exc).__name__}: {exc}); written at the end")

    def enqueue(started: _Started, runs: list[PlannedRun]) -> None:
        """`runs` of `started`'s sweep into the queue after the queued runs of that sweep and those before it."""
        at = sum(1 for queued, _ in queue if queued.index <= started.index)
        queue[at:at] = [(started, run) for run in runs]

    def start(index: int, path: Path, lanes: Lanes) -> None:
        try:
            sweep = load_sweep(path, sweeps_dir)
            echo(f"== campaign {campaign.name} ({tier}), sweep {index}/{len(campaign.sweeps)}: {sweep.name}")
            planned = prepare(sweep, tier, data_root, generate=False, reports_root=reports_root,
                              runs_root=runs_root, any_kind=any_kind)
            status = planned[1]
            if index not in generated and any(s == "dataset missing" for s in status.values()):
                if any(isinstance(what[0], int) for what in flying.values()):
                    deferred.append((index, path))  # one lane makes datasets at a time: two sweeps may need one
                    echo("  waits for the datasets a lane is making")
                    return
                generated.add(index)
                log = runs_root / sweep.name / tier / "datasets.log"
                echo(f"  making its datasets in a lane (progress: {log})")
                flying[lanes.submit(make_datasets, path, tier, data_root, sweeps_dir, reports_root, uri,
                                    log)] = (index, path)
                return
            begun = start_sweep(sweep, tier, data_root=data_root, runs_root=runs_root, progress=progress,
                                reports_root=reports_root, echo=echo, any_kind=any_kind, planned=planned)
        except KeyboardInterrupt:
            raise
        except Exception as exc:  # noqa: BLE001 - one sweep that cannot start is reported; the rest go on
            echo(f"  sweep {path.stem} failed: {type(exc).__name__}: {exc}")
            results[index] = SweepResult(path.stem, [], f"{type(exc).__name__}: {exc}")
            return
        started = _Started(index, path, sweep, begun.outcomes, begun.keep, len(begun.pending) + len(begun.branches))
        enqueue(started, begun.pending)  # a sweep whose data came late: ahead of later sweeps' runs
        for run in begun.branches:
            held.append((started, run))
            echo(f"  {run.name}: held; queued once that checkpoint is ready")
        if not started.left:
            finish(started)

    def release(give_up: bool = False) -> None:
        """Queue each held branch whose checkpoint is ready, after the queued runs of its sweep and those before
        it; `give_up`: nothing else is left to run, so the rest end WAITING."""
        ready = ready_branches([run for _, run in held], runs_root)
        for entry in list(held):
            started, run = entry
            if run in ready:
                held.remove(entry)
                enqueue(started, [run])
                echo(f"  {run.name} ({started.sweep.name}): its checkpoint is ready; queued")
            elif give_up:
                held.remove(entry)
                started.outcomes.append(waiting_outcome(run, runs_root))
                started.left -= 1
                echo(f"  {run.name} ({started.sweep.name}): still {started.outcomes[-1].error}")
                if not started.left:
                    finish(started)

    def ended(future: Future) -> None:
        what = flying.pop(future)
        if isinstance(what[0], int):  # datasets made (or not): start the sweep again, now with its data
            index, path = what
            again = [*deferred]  # the sweeps that waited for it start first, in the campaign's order
            deferred.clear()
            try:
                future.result()
                again.append((index, path))
            except Exception as exc:  # noqa: BLE001 - a dataset that would not generate fails its sweep
                echo(f"  sweep {path.stem} failed: its datasets: {type(exc).__name__}: {exc}")
                results[index] = SweepResult(path.stem, [], f"{type(exc).__name__}: {exc}")
            upcoming[:0] = sorted(again)
            return
        started, run = what
        outcome = as_outcome(run, outcome_of(future, run.name))
        started.outcomes.append(outcome)
        started.keep(outcome)
        started.left -= 1
        echo(f"  {run.name} ({started.sweep.name}): {outcome.status} after "
             f"{(time.perf_counter() - started_at) / 60:.1f} min of the campaign"
             + (f": {outcome.error}" if outcome.error else "")
             + f" ({len(flying)} running, {len(queue)} queued, {len(upcoming)} sweeps to start)")
        if started.left:
            _report_partway(started.path, tier, reports_root, echo, outcome, started.left)
        else:
            finish(started)

    with Lanes(parallel, echo) as lanes:
        while True:
            release()
            while len(flying) < parallel and (queue or upcoming):
                if queue and not (upcoming and upcoming[0][0] < queue[0][0].index):
                    started, run = queue.pop(0)
                    echo(f"  {run.name} ({started.sweep.name}) into a lane; progress: "
                         f"{run_dir(runs_root, run) / PROGRESS_LOG}")
                    flying[lanes.submit(job, run)] = (started, run)
                else:
                    start(*upcoming.pop(0), lanes)
            if not flying:
                release(give_up=True)  # queues any whose checkpoint came just now
                if not queue:
                    break
                continue
            done, _ = wait(flying, timeout=HELD_POLL_S if held else None, return_when=FIRST_COMPLETED)
            for future in done:
                ended(future)
    return [results[index] for index in sorted(results)]
