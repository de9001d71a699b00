"""`write_report`: a sweep's MLflow runs compiled into `reports/<sweep>/<tier>/README.md` plus figures.

Domain sweeps get the paper's Table 1 with our numbers beside it; ablation sweeps one figure per
axis (Fig. 4 style); every report a time-against-error figure and rollouts of its best run. Runs are read
through `gns_bench.tracking` (so a team server works as well as the local store); every number cites the
run id it came from, and every planned run appears, missing or failed ones marked so.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

from gns_bench.evaluate import metrics
from gns_bench.report import figures
from gns_bench.report.cells import (
    MISSING,
    against_cv,
    budget,
    budget_statement,
    comparable_cv,
    cv_ratio,
    fmt,
    ratio,
    run_id_cell,
    run_ids_cell,
    status_cell,
    steps_covered,
)
from gns_bench.report.collect import (
    METRICS,
    SUMMARY_FILE,
    RunRow,
    axis_value_label,
    collect,
    domain_sweeps,
    load_rollouts,
    mean_std,
    resolve_sweep,
    write_run_summary,
)
from gns_bench.report.reference import ablation_reference, domain_reference, inference_reference
from gns_bench.report.stability import sweep_section, write_stability_report
from gns_bench.report.study import candidates_section
from gns_bench.report.verdict import judge
from gns_bench.sweep.spec import SWEEPS_DIR, SweepSpec, discover_sweeps, load_sweep

# ----------------------------------------------------------------------------------------------
# Domain table (Table 1, App. C.4)
# ----------------------------------------------------------------------------------------------

DOMAIN_HEADER = ("| domain | simulator | dim | max N | K | one-step MSE (release's) | paper | ratio "
                 "| rollout MSE (release's) | paper | ratio "
                 "| constant velocity (GNS / it) | CConv rollout (paper) | OT | MMD | KE error | budget | status "
                 "| MLflow runs |")


def domain_row(sweep: SweepSpec, rows: list[RunRow]) -> str:
    ref = domain_reference(sweep.domain)
    one_step = mean_std([r.metric("one_step_mse") for r in rows])[0]
    rollout = mean_std([r.metric("rollout_mse") for r in rows])[0]
    # the trivial baseline on the same trajectories: a model that does not beat it has learned little dynamics
    constant_velocity = mean_std([r.metric("baseline_cv_rollout_mse") for r in rows])[0]
    baseline = "—" if not math.isfinite(constant_velocity) else f"{fmt(constant_velocity)} ({against_cv(rows)})"
    stopped = any(r.metric("rollout_stopped") > 0 for r in rows)  # NaN for runs that did not finish
    cells = [ref.name if ref else sweep.domain, ref.simulator if ref else "—", str(ref.dim) if ref else "—",
             f"{ref.max_particles:,}" if ref else "—", str(ref.sequence_length) if ref else "—",
             fmt(one_step), fmt(ref.one_step_mse) if ref else "—", ratio(one_step, ref.one_step_mse if ref else None),
             fmt(rollout), fmt(ref.rollout_mse) if ref else "—",
             ratio(rollout, ref.rollout_mse if ref else None) + (" (stopped rollouts)" if stopped and ref else ""),
             baseline,
             fmt(ref.cconv_rollout_mse) if ref and ref.cconv_rollout_mse else "—",
             *(fmt(mean_std([r.metric(m) for r in rows])[0]) for m in ("ot", "mmd", "kinetic_energy_error")),
             budget(rows), status_cell(rows), run_ids_cell(rows)]
    if not any(r.ok for r in rows):
        cells[5] = cells[8] = MISSING
    return "| " + " | ".join(cells) + " |"


def domain_table(collected: list[tuple[SweepSpec, list[RunRow]]]) -> list[str]:
    lines = [DOMAIN_HEADER, "|" + "---|" * DOMAIN_HEADER.count(" | ") + "---|"]
    lines += [domain_row(sweep, rows) for sweep, rows in collected]
    return lines


def inference_section(collected: list[tuple[SweepSpec, list[RunRow]]]) -> list[str]:
    lines = ["## Rollout time per step (App. C.6)", "",
             "| domain | ours (s/step) | hardware | paper GNS (s/step, V100) | paper solver (s/step, CPU) |",
             "|---|---|---|---|---|"]
    for sweep, rows in collected:
        ref = domain_reference(sweep.domain)
        paper = inference_reference(ref.dim, ref.simulator) if ref else None
        ours = mean_std([r.metric("rollout_seconds_per_step") for r in rows])[0]
        hardware = "; ".join(sorted({r.tag("hardware", "?") for r in rows if r.ok})) or "—"
        ours_cell = fmt(ours) if any(r.ok for r in rows) else MISSING
        gns, solver = ((f"{paper[k][0]:g}-{paper[k][1]:g}" for k in ("gns_seconds", "solver_seconds")) if paper
                       else ("—", "—"))
        lines.append(f"| {ref.name if ref else sweep.domain} | {ours_cell} | {hardware} | {gns} | {solver} |")
    return lines + ["", "The paper's times are per step on a V100 (GNS) and a 6-core CPU (solver), ranges over its "
                        "domains of that kind; ours are on the hardware listed, at our model and dataset size."]


# ----------------------------------------------------------------------------------------------
# Ablations (Sec. 5.4, Fig. 4; App. C.1)
# ----------------------------------------------------------------------------------------------

def ablation_section(sweep: SweepSpec, rows: list[RunRow], out_dir: Path) -> list[str]:
    lines = []
    for axis in sweep.axes:
        values = list(dict.fromkeys(r.planned.axes[axis] for r in rows))
        stats = {m: [mean_std([r.metric(m) for r in rows if r.planned.axes[axis] == v]) for v in values]
                 for m, _ in figures.PANELS}
        reference = ablation_reference(axis)
        name = axis.split(".")[-1]
        figure = figures.ablation_figure(axis, values, stats, reference, out_dir / f"ablation_{name}.png")
        default = axis_value_label(reference["default"]) if "default" in reference else "none given"
        lines += [f"## {axis}", "", f"Paper default: {default} (dashed line); x scale: {reference['scale']}; "
                  "error bars: std over seeds.", "", f"![{axis}]({figure.name})", ""]
        if any(r.metric("rollout_stopped") > 0 for r in rows):
            lines += ["A health monitor stopped some rollouts, so rollout MSE, OT and MMD cover different steps in "
                      "different runs (column *rollout steps*). *vs constant velocity* divides the rollout MSE by "
                      "constant velocity's over the same steps: that column compares runs like for like.", ""]
        lines += ["| value | seeds | one-step MSE | rollout MSE | OT | MMD | rollout steps | vs constant velocity |",
                  "|---|---|---|---|---|---|---|---|"]
        for i, value in enumerate(values):
            at_value = [r for r in rows if r.planned.axes[axis] == value]
            seeds = stats["rollout_mse"][i][2]
            cells = [f"{fmt(stats[m][i][0])} ± {fmt(stats[m][i][1])}" if stats[m][i][2] else MISSING
                     for m, _ in figures.PANELS]
            cells += [steps_covered(at_value), cv_ratio(at_value) if seeds else MISSING]
            lines.append(f"| {axis_value_label(value)} | {seeds}/{len(at_value)} | " + " | ".join(cells) + " |")
        lines += ["", verdict_line(axis, values, rows, reference), ""]
    return lines


def verdict_line(axis: str, values: list, rows: list[RunRow], reference: dict) -> str:
    """The computed verdict on the paper's finding for this axis (gns_bench/report/verdict.py)."""
    if "better" not in reference and not reference.get("no_effect"):
        return f"**Verdict ({axis}):** the paper states no finding on this axis to compare with."
    errors = {value: [r.metric("rollout_mse") / comparable_cv(r) for r in rows
                      if r.planned.axes[axis] == value and comparable_cv(r) > 0] for value in values}
    outcome = judge(errors, reference)
    return (f"**Verdict ({axis}): {outcome.verdict}.** Paper: {reference.get('summary', '—')}. Ours: {outcome.detail}; "
            "error = rollout MSE / constant velocity's over the same steps.")


def runs_table(sweep: SweepSpec, rows: list[RunRow]) -> list[str]:
    header = ["run", *[a.split(".")[-1] for a in sweep.axes], "seed", "status", "MLflow run id", *METRICS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        cells = [r.planned.name, *[axis_value_label(r.planned.axes[a]) for a in sweep.axes], str(r.planned.seed),
                 "ok" if r.ok else f"**{r.status}**", run_id_cell(r),
                 *(fmt(r.metric(m)) for m in METRICS)]
        lines.append("| " + " | ".join(cells) + " |")
    settings = sorted({distribution_settings(r) for r in rows if r.ok})
    lines += ["", "OT: exact EMD (W2^2: squared Euclidean cost, uniform weights, POT) between the moving particles' "
              "clouds, subsampled to at most `eval.distribution_max_particles`; MMD: Gaussian kernel of width "
              "`eval.mmd_bandwidth_radii` x R; both averaged over `eval.distribution_steps` evenly spaced rollout "
              "steps.",
              "", *(f"- {setting}" for setting in settings)]
    return lines


def distribution_settings(row: RunRow) -> str:
    """How a run's OT and MMD were computed, from its logged params and its `ot_exact` metric: below 1 only
    for runs evaluated when clouds above `eval.ot_exact_max_particles` got a Sinkhorn divergence (biased low,
    0.2-0.55x EMD), before OT was exact at every size."""
    exact = row.metric("ot_exact")
    method = ("exact EMD" if exact == 1 else "—" if not math.isfinite(exact) else
              f"Sinkhorn divergence (sinkhorn_reg {row.param('eval.sinkhorn_reg', '?')}, above "
              f"{row.param('eval.ot_exact_max_particles', '?')} particles) on {1 - exact:.0%} of trajectories")
    return (f"OT method: {method}; MMD bandwidth "
            f"{row.param('eval.mmd_bandwidth_radii', '?')} R; {row.param('eval.distribution_steps', '?')} steps; "
            f"at most {row.param('eval.distribution_max_particles', '?')} particles")


# ----------------------------------------------------------------------------------------------
# Shared sections: time against error, rollouts
# ----------------------------------------------------------------------------------------------

def time_section(rows: list[RunRow], out_dir: Path, label=lambda r: r.planned.name) -> list[str]:
    points = [(label(r), r.metric("train/wall_time_s"), r.metric("rollout_seconds_per_step"), r.metric("rollout_mse"))
              for r in rows if r.ok]
    if not points:
        return ["## Time against error", "", "No finished run.", ""]
    figure = figures.time_error_figure(points, out_dir / "time_vs_error.png")
    return ["## Time against error", "", "Training wall time and rollout time per step against rollout MSE, one "
            "point per run; the Pareto front (no run both faster and more accurate) in red.", "",
            f"![time against error]({figure.name})", ""]


def rollout_section(rows: list[RunRow], out_dir: Path) -> list[str]:
    """Best and worst test trajectories of the run with the lowest rollout MSE, as PNG and GIF."""
    done = sorted((r for r in rows if r.ok and math.isfinite(r.metric("rollout_mse"))),
                  key=lambda r: r.metric("rollout_mse"))
    lines = ["## Rollouts", ""]
    if not done:
        return lines + ["No finished run with rollouts.", ""]
    row = done[0]
    with tempfile.TemporaryDirectory() as tmp:
        results = [r for r in load_rollouts(row.artifact_run_id, f"evaluation/{row.split}_rollouts.npz", Path(tmp))
                   if r.predicted.shape[0]]
    if not results:
        return lines + [f"Run {run_id_cell(row)} logged no rollouts.", ""]
    errors = [metrics.rollout_mse(r.predicted, r.ground_truth[: r.predicted.shape[0]], r.scored_mask())
              for r in results]
    lines.append(f"From run {run_id_cell(row)} ({row.planned.name}, lowest rollout MSE), split '{row.split}': "
                 "ground truth above / left, GNS below / right.")
    lines.append("")
    for label, index in (("best", int(np.argmin(errors))), ("worst", int(np.argmax(errors)))):
        title = f"{label}: trajectory {index}, rollout MSE {errors[index]:.3g}"
        png = figures.rollout_png(results[index], out_dir / f"rollout_{label}.png", title)
        gif = figures.rollout_gif(results[index], out_dir / f"rollout_{label}.gif", title)
        lines += [f"**{title}**", "", f"![{label} rollout]({png.name})", "", f"![{label} animation]({gif.name})", ""]
    return lines


# ----------------------------------------------------------------------------------------------
# Entry points
# ----------------------------------------------------------------------------------------------

def _write(out_dir: Path, lines: list[str]) -> Path:
    path = out_dir / "README.md"
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path


def write_sweep_report(sweep: SweepSpec, tier: str, out_dir: Path, rows: list[RunRow] | None = None) -> Path:
    """The sweep's report from `rows` (its collected runs; collected here when not given)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = collect(sweep, tier, out_dir.parent.parent) if rows is None else rows
    write_run_summary(out_dir / SUMMARY_FILE, sweep, tier, rows)
    lines = [f"# {sweep.name} ({tier} tier)", "", f"{sweep.description}. Domain `{sweep.domain}`; paper: "
             f"{sweep.paper_figure or '—'}. MLflow experiment `{sweep.experiment}`; {len(rows)} planned runs, "
             f"{sum(r.ok for r in rows)} finished.", "", budget_statement(rows), ""]
    if sweep.kind == "stress":
        lines += sweep_section(sweep, rows, out_dir)
    elif sweep.kind == "domain":
        lines += ["## Against the paper (App. C.4)", "", *domain_table([(sweep, rows)]), ""]
    elif sweep.candidates:
        lines += candidates_section(sweep, tier, rows, out_dir)
    else:
        lines += ablation_section(sweep, rows, out_dir)
    lines += ["## Runs", "", *runs_table(sweep, rows), "", *time_section(rows, out_dir),
              *rollout_section(rows, out_dir)]
    return _write(out_dir, lines)


def write_domains_report(sweeps: list[SweepSpec], tier: str, out_dir: Path) -> Path:
    """The paper's domain table across domain sweeps, ours beside it, one row per sweep (missing ones too)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    collected = [(s, collect(s, tier, out_dir.parent.parent)) for s in sweeps]
    every = [r for _, rows in collected for r in rows]
    lines = [f"# Domains ({tier} tier)", "",
             "The paper's results on its 16 domains (Table 1, App. C.4) "
             "with our numbers beside them: mean over seeds of the test-split metrics, MSEs absolute (not "
             "x1e-9 / x1e-3); ratio = ours / paper. CConv: the paper's best CConv baseline (Sec. 5.5 and "
             "App. D.1, approximate). Each row states its budget. Per-domain runs "
             f"and rollouts: `reports/domain-<id>/{tier}/` (`gns-bench report domain-<id> --tier {tier}`).", "",
             budget_statement(every), "", *domain_table(collected), "", *inference_section(collected), "",
             *time_section(every, out_dir, label=lambda r: r.planned.sweep.removeprefix("domain-"))]
    return _write(out_dir, lines)


def write_report(sweep: str | Path, tier: str = "smoke", reports_root: Path = Path("reports")) -> Path:
    """Write `reports_root/<sweep name>/<tier>/README.md` (+ PNG/GIF) from MLflow; returns the README path.

    `sweep` is a sweep file, a sweep name (`ablation-noise_std`, `domain-goop`), `domains` for the table
    across all domain sweeps, or `stability` for the stress sweeps' report (`write_all_reports` writes them all).
    """
    reports_root = Path(reports_root)
    if str(sweep) == "domains":
        return write_domains_report(domain_sweeps(), tier, reports_root / "domains" / tier)
    if str(sweep) == "stability":
        return write_stability_report(tier, reports_root / "stability" / tier)
    spec = resolve_sweep(sweep)
    return write_sweep_report(spec, tier, reports_root / spec.name / tier)


def write_all_reports(tier: str = "smoke", reports_root: Path = Path("reports"),
                      sweeps_dir: Path = SWEEPS_DIR) -> list[Path]:
    """The report of every sweep in `sweeps_dir` that has runs at `tier`, then the domain table and the
    stability report (those two always, gaps shown as missing). Returns the README paths in that order."""
    written = []
    for path in discover_sweeps(sweeps_dir):
        spec = load_sweep(path)
        rows = collect(spec, tier, reports_root)
        if any(row.record for row in rows):
            written.append(write_sweep_report(spec, tier, reports_root / spec.name / tier, rows))
    written.append(write_domains_report(domain_sweeps(), tier, reports_root / "domains" / tier))
    written.append(write_stability_report(tier, reports_root / "stability" / tier))
    return written
