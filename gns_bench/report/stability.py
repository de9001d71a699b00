"""The stress sweeps' (`sweeps/stress/`) reports: each sweep's own section (`sweep_section`, in its report) and
the stability page that sums them up and links to them.

Per trained domain: the largest stable horizon and scale, error against time for each stress test, the
monitors that tripped and where, and frames of each generalisation rollout next to its ground truth. Read from
MLflow (metrics, tags, and the curves each test logged as `stress/<test>.json`), or, once the store is gone,
from the report's run summary, which keeps the tests' results and what was drawn.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import math
import tempfile
from pathlib import Path

import numpy as np

from gns_bench import tracking
from gns_bench.data.format import RIGID_PARTICLE_TYPE
from gns_bench.evaluate import metrics
from gns_bench.evaluate.plots import flag_marks
from gns_bench.evaluate.result import StressResult
from gns_bench.evaluate.stress_plots import plot_stress
from gns_bench.report import figures
from gns_bench.report.cells import budget, budget_statement, fmt
from gns_bench.report.collect import RunRow, collect, load_rollouts, stress_sweeps
from gns_bench.report.figures import RIGIDITY_WORDS
from gns_bench.report.kept import read_kept
from gns_bench.sweep.spec import SweepSpec


def load_results(row: RunRow, workdir: Path) -> list[StressResult]:
    """The stress tests a run logged, from its `stress/<test>.json` artifacts."""
    results = []
    for name in filter(None, row.tag("stress/tests").split(",")):
        local = tracking.download_artifacts(row.stress_run_id, f"stress/{name}.json", workdir)
        if local is None:
            continue
        data = json.loads(local.read_text())
        results.append(StressResult(data["name"], data["metrics"], data["curves"], data["trips"], data["notes"]))
    return results


def stable_cells(row: RunRow, saved_lengths: list[int] | None = None) -> tuple[str, str]:
    """'largest stable horizon' and 'largest stable scale' cells of one run (`saved_lengths`: what
    `_rollout_lengths` gave when its rollouts could still be downloaded, from the run summary)."""
    steps, length = row.metric("stress/horizon/stable_steps"), row.metric("stress/horizon/training_length")
    total = row.metric("stress/horizon/steps")
    if math.isfinite(steps):
        horizon = f"{steps / length:.2g}x ({steps:.0f} of {total:.0f} steps" + \
                  (", no monitor tripped)" if steps >= total else ", a monitor stopped it)")
        unstable_at_training_length = steps < min(total, length)  # a monitor stopped it that early
    else:
        horizon, unstable_at_training_length = _evaluation_horizon(row, saved_lengths)
    factor = row.metric("stress/scale/largest_stable_factor")
    if math.isfinite(factor):
        particles = row.metric(f"stress/scale/x{factor:g}/particles") if factor else math.nan
        scale = f"{factor:g}x ({particles:,.0f} particles)" if factor else "none stable"
    elif unstable_at_training_length:
        # A scale counts as stable when its rollouts run their whole length; this model's rollouts already
        # stop within the training length at the training scale, so no scale (1x included) qualifies.
        scale = "none: unstable at the training scale already (horizon < 1x); no larger scene run"
    else:
        scale = "not run"
    return horizon, scale


def _evaluation_horizon(row: RunRow, saved_lengths: list[int] | None = None) -> tuple[str, bool]:
    """Without a horizon test, the test split's evaluation rollouts still bound the stable horizon: the fewest
    steps any of them ran before a monitor stopped it, as a multiple of the training length when they ran
    whole trajectories (`eval.rollout_steps` unset). Also: whether a monitor stopped one, or flagged one (a
    monitor outside `eval.stop_on` tripped and the rollout ran on: not stable either)."""
    lengths = _rollout_lengths(row.artifact_run_id, row.split) or (tuple(saved_lengths) if saved_lengths else None)
    if lengths is None:
        return "not run", False
    count, ran, full = lengths
    rollouts = f"the {count} test rollout{'s' if count != 1 else ''}"
    stopped = ran < full
    fraction = row.metric("rollout_stopped")  # the mean over the rollouts of 1 (stopped) or 0
    what = (f"a monitor stopped {round(fraction * count)} of {count}" if math.isfinite(fraction) and fraction > 0
            else "a monitor stopped at least one")
    flagged = row.metric("rollout_flagged") > 0
    quiet = (f"no monitor stopped one, but one flagged one (`{row.split}/rollouts_flagged`)" if flagged
             else "no monitor tripped")
    if row.param("eval.rollout_steps", "None") not in ("", "None"):  # cut short: no multiple of the length
        return (f"{ran} of {full} steps of {rollouts} (evaluation cut at {full} steps), {what if stopped else quiet}",
                stopped or flagged)
    if not stopped:
        if flagged:
            return f"< 1x ({full} steps of {rollouts}, {quiet}; no longer scene run)", True
        return f">= 1x ({full} steps of {rollouts}, no monitor tripped; no longer scene run)", False
    return (f"{ran / full:.2g}x (the shortest ran {ran} of {full} steps of {rollouts}, {what}; "
            "no longer scene run)", True)


@functools.lru_cache(maxsize=256)
def _rollout_lengths(run_id: str, split: str) -> tuple[int, int, int] | None:
    """(rollouts, fewest predicted steps, fewest ground-truth steps) of a run's evaluation rollouts, downloaded
    once per run: the summary table and the run's own section both ask."""
    with tempfile.TemporaryDirectory() as tmp:
        results = load_rollouts(run_id, f"evaluation/{split}_rollouts.npz", Path(tmp))
    if not results:
        return None
    return (len(results), min(r.predicted.shape[0] for r in results), min(r.ground_truth.shape[0] for r in results))


def trips(row: RunRow) -> list[str]:
    """Every monitor stop (and flag) recorded on a run: evaluation, stress tests and generalisation rollouts."""
    return [f"`{key}`: {value}" for key, value in sorted(row.record.tags.items())
            if key.endswith(("rollouts_stopped", "rollouts_flagged", "/trips"))] if row.record else []


def _per_trajectory(row: RunRow, variant: str, workdir: Path) -> list[dict[str, float]]:
    local = tracking.download_artifacts(row.stress_run_id, f"generalisation/{variant}/{variant}_per_trajectory.csv",
                                        workdir)
    if local is None:
        return []
    with local.open() as f:
        return [{k: float(v) for k, v in r.items() if v not in ("", None)} for r in csv.DictReader(f)]


def context_figure(rows: list[dict[str, float]], path: Path, held_out: tuple[float, float] | None) -> Path:
    """Rollout MSE against the per-trajectory context (friction angle), the held-out interval shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.array([r["context"] for r in rows])
    fig, ax = plt.subplots(figsize=(4.8, 3.2))
    for key, label in (("rollout_mse", "GNS"), ("baseline_cv_same_steps_mse", "constant velocity, same steps")):
        y = np.array([r.get(key, math.nan) for r in rows])
        order = np.argsort(x)
        ax.plot(x[order], y[order], "o-", ms=4, lw=1, label=label)
    if held_out:
        ax.axvspan(*held_out, color="grey", alpha=0.2, label="held out in training")
    ax.set_yscale("log")
    ax.set(xlabel="friction angle (degrees)", ylabel="rollout MSE", title="error against the friction angle")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def held_out_interval(domain: str) -> tuple[float, float] | None:
    """The context interval (e.g. friction angles, App. C.5) the domain's training data leaves out, if any."""
    try:
        from gns_bench.physics.spec import load_domain_spec

        context = load_domain_spec(domain).context
    except Exception:  # noqa: BLE001 - the tiny domain has no spec file
        return None
    return context.exclude[0] if context is not None and context.exclude else None


def sweep_section(sweep: SweepSpec, rows: list[RunRow], out_dir: Path, level: str = "##",
                  statement: bool = False, saved: dict | None = None) -> tuple[list[str], dict]:
    """One stress sweep: budget (and, with `statement`, what it means against the paper's), stability
    summary, each test's figure and numbers, generalisation frames. Returns the lines and what a run summary
    must keep to write them again once MLflow no longer holds the runs (`saved` is that, from the last report:
    per run id, its tests' results, the per-trajectory generalisation rows and which pictures were drawn)."""
    lines = [f"{level} {sweep.name}: {sweep.description}", "", f"Paper: {sweep.paper_figure or '—'}. Domain "
             f"`{sweep.domain}`; MLflow experiment `{sweep.experiment}`.", ""]
    saved, kept = saved or {}, {}
    done = [r for r in rows if r.ok]
    if not done:
        states = ", ".join(sorted({r.status for r in rows})) or "missing"
        return lines + [f"**No finished run at this tier ({states}).** Run `nox -s {sweep.name} -- <tier>`.", ""], kept
    lines += [f"Training: {budget(done)}." + (f" {budget_statement(done)}" if statement else ""), ""]
    for row in done:
        before = saved.get(row.run_id, {})
        lengths = None
        if not math.isfinite(row.metric("stress/horizon/stable_steps")):  # the evaluation bounds the horizon
            lengths = _rollout_lengths(row.artifact_run_id, row.split) or before.get("rollout_lengths")
        horizon, scale = stable_cells(row, lengths)
        lines += [f"Run `{row.run_id}` ({row.planned.name}): largest stable horizon **{horizon}**; largest stable "
                  f"scale **{scale}**. Tests skipped: {row.tag('stress/skipped') or 'none'}.", ""]
        stops = trips(row)
        lines += ["Monitors that stopped rollouts (or, tags ending `rollouts_flagged`, flagged them as they ran on):",
                  "", *(f"- {s}" for s in stops), ""] if stops else \
            ["No health monitor tripped in any of this run's rollouts.", ""]
        with tempfile.TemporaryDirectory() as tmp:
            workdir = Path(tmp)
            results = load_results(row, workdir) or [StressResult(**r) for r in before.get("tests", [])]
            # Curves in one order, however they were read (the run summary's JSON sorts keys): same figures.
            results = [dataclasses.replace(r, curves=dict(sorted(r.curves.items())),
                                           metrics=dict(sorted(r.metrics.items()))) for r in results]
            for result in results:
                training = int(row.metric("stress/horizon/training_length")) if result.name == "horizon" else None
                figure = plot_stress(result, out_dir / f"{sweep.name}_{result.name}.png", training_length=training,
                                     title=f"{sweep.name}: {result.name}")
                lines += [f"{level}# {result.name}", "", f"![{result.name}]({figure.name})", "",
                          "| metric | value |", "|---|---|",
                          *(f"| {k} | {fmt(v)} |" for k, v in sorted(result.metrics.items())), ""]
                lines += [f"- {note}" for note in result.notes] + ([""] if result.notes else [])
            general, drawn = generalisation_lines(sweep, row, out_dir, workdir, level, before.get("generalisation", {}))
            lines += general
        kept[row.run_id] = {"tests": [dataclasses.asdict(r) for r in results], "generalisation": drawn,
                            **({"rollout_lengths": list(lengths)} if lengths else {})}
    return lines, kept


def generalisation_lines(sweep: SweepSpec, row: RunRow, out_dir: Path, workdir: Path, level: str,
                         saved: dict | None = None) -> tuple[list[str], dict]:
    """Each generalisation dataset's numbers, error against its context and one rollout drawn; with what was
    drawn per dataset (kept in the run summary: `saved` stands in for MLflow's artifacts once they are gone)."""
    lines, drawn, saved = [], {}, saved or {}
    for variant in filter(None, row.tag("generalisation/datasets").split(",")):
        prefix = f"generalisation/{variant}/"
        before = saved.get(variant, {})
        values = {k[len(prefix):]: v for k, v in row.record.metrics.items() if k.startswith(prefix)}
        for key in ("rollout_stopped", "rollout_flagged"):  # logged as the fraction of rollouts: shown as a count
            values[key] = values.get(key, math.nan) * values.get("num_trajectories", math.nan)
        lines += [f"{level}# generalisation: {variant}", "",
                  "| rollout MSE | constant velocity, same steps | one-step MSE | OT | MMD | rollouts stopped "
                  "| rollouts flagged "
                  "| trajectories |",
                  "|---|---|---|---|---|---|---|---|",
                  "| " + " | ".join(fmt(values.get(k, math.nan)) for k in (
                      "rollout_mse", "baseline_cv_same_steps_mse", "one_step_mse", "ot", "mmd", "rollout_stopped",
                      "rollout_flagged", "num_trajectories")) + " |", ""]
        per_trajectory = _per_trajectory(row, variant, workdir) or before.get("per_trajectory", [])
        if per_trajectory and all("context" in r for r in per_trajectory):
            figure = context_figure(per_trajectory, out_dir / f"{sweep.name}_{variant}_context.png",
                                    held_out_interval(sweep.domain))
            lines += [f"![error against the context]({figure.name})", ""]
        npz = f"generalisation/{variant}/{variant}_rollouts.npz"
        loaded = load_rollouts(row.stress_run_id, npz, workdir)
        results = {i: r for i, r in enumerate(loaded) if r.predicted.shape[0]}  # trajectory number -> rollout
        picture, rigidity = before.get("picture", False), before.get("rigidity", False)
        if results:
            errors = {i: metrics.rollout_mse(r.predicted, r.ground_truth[: r.predicted.shape[0]], r.scored_mask())
                      for i, r in results.items()}
            best = min(errors, key=errors.get)
            steps = results[best].predicted.shape[0]
            title = f"{variant}: trajectory {best}, MSE {errors[best]:.3g} over {steps} steps"
            marks = flag_marks(row.tag(f"generalisation/{variant}/rollouts_flagged")).get(best, {})
            figures.rollout_png(results[best], out_dir / f"{sweep.name}_{variant}.png", title, marks=marks)
            picture = True
            rigidity = figures.rigidity_figure(list(loaded), RIGID_PARTICLE_TYPE,
                                               out_dir / f"{sweep.name}_{variant}_rigidity.png") is not None
        picture = picture and (out_dir / f"{sweep.name}_{variant}.png").is_file()
        rigidity = rigidity and (out_dir / f"{sweep.name}_{variant}_rigidity.png").is_file()
        if picture:
            lines += ["Ground truth and GNS on one frame:", "", f"![{variant}]({sweep.name}_{variant}.png)", ""]
        if rigidity:
            lines += [f"Rigid-body drift ({RIGIDITY_WORDS}):", "",
                      f"![{variant}: rigid-body drift]({sweep.name}_{variant}_rigidity.png)", ""]
        drawn[variant] = {"per_trajectory": per_trajectory, "picture": picture, "rigidity": rigidity}
    return lines, drawn


def write_stability_report(tier: str, out_dir: Path, sweeps: list[SweepSpec] | None = None) -> Path:
    """`reports/stability/<tier>/README.md`: every stress sweep, missing ones marked."""
    out_dir.mkdir(parents=True, exist_ok=True)
    sweeps = stress_sweeps() if sweeps is None else sweeps
    collected = [(s, collect(s, tier, out_dir.parent.parent)) for s in sweeps]
    lines = [f"# Stability and generalisation ({tier} tier)", "",
             budget_statement([r for _, rows in collected for r in rows], tier), "",
             "The paper's stability and generalisation claims (Sec. 5.3) and failure "
             "modes (App. C.7), each a stress sweep in "
             "`sweeps/stress/` run with `nox -s <sweep> -- <tier>`. Tests: `horizon` (rollouts longer than "
             "training), `precision` (fp64 / fp32 / bf16), `perturbation` (growth of a small initial "
             "perturbation, model against solver), `scale` (scenes with more particles in larger arenas); "
             "generalisation rollouts on unseen scenes. Health monitors (non-finite, out of bounds, energy "
             "blow-up, density collapse) run in every rollout and stop it when they trip.", "",
             "## Largest stable horizon and scale", "",
             "| sweep | domain | horizon | scale | monitors tripped | budget | MLflow run |",
             "|---|---|---|---|---|---|---|"]
    for sweep, rows in collected:
        done = [r for r in rows if r.ok]
        if not done:
            states = ", ".join(sorted({r.status for r in rows})) or "missing"
            lines.append(f"| {sweep.name} | {sweep.domain} | **{states}** | **{states}** | — | — | — |")
        saved = read_kept(out_dir.parent.parent / sweep.name / tier).get("stress") or {}
        for row in done:
            horizon, scale = stable_cells(row, saved.get(row.run_id, {}).get("rollout_lengths"))
            lines.append(f"| {sweep.name} | {sweep.domain} | {horizon} | {scale} | {len(trips(row))} | "
                         f"{budget([row])} | `{row.run_id}` |")
    lines += ["", "Each sweep's tests, figures and generalisation rollouts are in its own report:", ""]
    for sweep, _ in collected:
        lines.append(f"- [{sweep.name}](../../{sweep.name}/{tier}/README.md): {sweep.description}")
    path = out_dir / "README.md"
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path
