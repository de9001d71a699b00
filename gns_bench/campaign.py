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

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from gns_bench.report import write_all_reports, write_overviews, write_report
from gns_bench.sweep.campaigns import Campaign
from gns_bench.sweep.runner import RunOutcome, format_plan, prepare, run_sweep
from gns_bench.sweep.spec import SWEEPS_DIR, SweepSpec, load_sweep
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


def run_campaign(campaign: Campaign, tier: str, *, data_root: Path, runs_root: Path,
                 reports_root: Path = Path("reports"), launcher: str = "local", cluster: str | None = None,
                 progress: bool = True, echo: Callable[[str], None] = print,
                 sweeps_dir: Path = SWEEPS_DIR, parallel: int = 1, any_kind: bool = False) -> list[SweepResult]:
    """Run every sweep of the campaign at `tier` in order, writing each one's report and the overviews when it
    is done, then every report (`write_all_reports`). `parallel`: runs at once
    within each sweep (`run_sweep`). Runs held to another kind of machine wait for a session on one
    (`sweep/cpu_kinds.py`) while the campaign goes on with the rest, unless `any_kind`."""
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
        summary = summary_path(reports_root, sweep.name, tier)
        held = read_run_summary(summary)
        readme = summary.parent / "README.md"
        if (all(o.status == "WAITING" or (o.status == "SKIPPED" and o.name in held) for o in outcomes)
                and summary.is_file()
                and readme.is_file() and readme.stat().st_mtime >= summary.stat().st_mtime):
            # nothing ran or was recorded, its summary holds every run not waiting for another kind of machine,
            # and its report was written after the summary last changed: the report and the overviews stand as
            # written, and the final rewrite below covers them. Rewriting them took about 20 s a sweep (MLflow
            # reads, PNGs): a resumed campaign spent 4.5 min skipping the 13 sweeps it had done (2-core AMD EPYC,
            # CPU family 25, model 17).
            echo(f"  reports: unchanged, nothing new in {sweep.name}")
            continue
        for written in [write_report(path, tier, reports_root), *write_overviews(tier, reports_root)]:
            echo(f"  report: {written}")
    for written in write_all_reports(tier, reports_root, sweeps_dir):
        echo(f"  report: {written}")
    return results
