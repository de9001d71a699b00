"""`write_report`: a sweep's MLflow runs compiled into `reports/<sweep>/<tier>/README.md` plus figures.

Domain sweeps get the paper's Knowl 5 table with our numbers beside it; ablation sweeps one figure per
axis (Fig. 4 style); every report a time-against-error figure and rollouts of its best run. Runs are read
through `gns_bench.tracking` (so a team server works as well as the local store); every number cites the
run id it came from, and every planned run appears, missing or failed ones marked so.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

from gns_bench import tracking
from gns_bench.evaluate import metrics
from gns_bench.evaluate.rollout import RolloutResult
from gns_bench.report import figures
from gns_bench.report.collect import (
    METRICS,
    RunRow,
    axis_value_label,
    collect,
    domain_sweeps,
    mean_std,
    resolve_sweep,
)
from gns_bench.report.reference import ablation_reference, domain_reference, inference_reference, paper_training_steps
from gns_bench.sweep.spec import SWEEPS_DIR, SweepSpec, discover_sweeps, load_sweep

MISSING = "**missing**"


def fmt(value: float) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.3g}"


def ratio(ours: float, paper: float | None) -> str:
    if paper is None or not math.isfinite(ours) or paper == 0:
        return "—"
    return f"{ours / paper:.3g}x"


def _status_cell(rows: list[RunRow]) -> str:
    if not rows or not any(r.ok for r in rows):
        states = sorted({r.status for r in rows}) or ["missing"]
        return "**" + ", ".join(states) + "**"
    bad = [r for r in rows if not r.ok]
    return "ok" if not bad else f"ok ({len(bad)} of {len(rows)} {', '.join(sorted({r.status for r in bad}))})"


def run_id_cell(row: RunRow) -> str:
    """The run id, with its status when it did not finish, and the run it copies when another sweep trained it."""
    if not row.run_id:
        return "—"
    source = row.tag("shared_from")
    return (f"`{row.run_id}`" + ("" if row.ok else f" ({row.status})")
            + (f", shared from {row.tag('shared_from_run', '?')} (`{source}`)" if source else ""))


def _run_ids(rows: list[RunRow]) -> str:
    return "<br>".join(run_id_cell(r) for r in rows if r.run_id) or "—"


def comparable_cv(row: RunRow) -> float:
    """The constant-velocity rollout MSE over the steps this run's GNS rollouts covered: the whole horizon, or
    the steps before a monitor's stop; NaN for a stopped run evaluated before that was logged."""
    same_steps = row.metric("baseline_cv_same_steps_mse")
    if math.isfinite(same_steps):
        return same_steps
    return math.nan if row.metric("rollout_stopped") > 0 else row.metric("baseline_cv_rollout_mse")


def _paired_with_cv(rows: list[RunRow]) -> list[RunRow]:
    """The runs whose constant-velocity MSE over the GNS rollouts' own steps is known."""
    return [r for r in rows if comparable_cv(r) > 0]  # NaN (not finished, not logged) fails the test


def cv_ratio(rows: list[RunRow]) -> str:
    """GNS / constant-velocity rollout MSE (means over runs), both over the same steps; "—" where unknown."""
    paired = _paired_with_cv(rows)
    if not paired:
        return "—"
    return ratio(mean_std([r.metric("rollout_mse") for r in paired])[0],
                 mean_std([comparable_cv(r) for r in paired])[0])


def _against_cv(rows: list[RunRow]) -> str:
    """`cv_ratio` in words, for the domain table's baseline cell."""
    paired = _paired_with_cv(rows)
    if not paired:
        return "GNS rollouts stopped" if any(r.metric("rollout_stopped") > 0 for r in rows) else "—"
    return cv_ratio(paired) + (" over the steps before the stops"
                               if any(r.metric("rollout_stopped") > 0 for r in paired) else "")


def steps_covered(rows: list[RunRow]) -> str:
    """Mean number of steps the finished runs' rollouts covered, and the share a monitor stopped."""
    steps, _, n = mean_std([r.metric("rollout_steps") for r in rows])
    if not n:
        return MISSING if not any(r.ok for r in rows) else "—"
    stopped = mean_std([r.metric("rollout_stopped") for r in rows])[0]
    return f"{steps:.0f}" + (f" ({stopped:.0%} stopped)" if stopped > 0 else "")


def budget(rows: list[RunRow]) -> str:
    """Training steps, wall time, hardware and dataset tier of the finished runs in a row."""
    done = [r for r in rows if r.ok]
    if not done:
        return "—"
    steps = sorted({int(float(r.param("train.steps", "0"))) for r in done})
    wall = mean_std([r.metric("train/wall_time_s") for r in done])[0]
    hardware = sorted({r.tag("hardware", "?") for r in done})
    tiers = sorted({r.tag("dataset_tier") or r.param("sweep.dataset_tier", "?") for r in done})
    horizon = mean_std([r.metric("rollout_steps") for r in done])[0]
    models = sorted({f"M={r.param('model.message_passing_steps', '?')}, latent {r.param('model.latent_size', '?')}"
                     for r in done})
    # fp32 (the paper's) unless a run trained in reduced precision; torch.compile changes speed, not the function
    precisions = sorted({r.param("train.precision", "fp32") + (" compiled" if r.param("train.compile") == "True"
                                                                else "") for r in done})
    if precisions != ["fp32"]:
        models = [f"{m}, {'/'.join(precisions)}" for m in models]
    # Where the schedule stood at the last step: short runs on the paper's 5M-step decay end at ~1e-4, and
    # their last weights are a noisy snapshot (sweeps/tiers.toml, small tier)
    final_rates = sorted({fmt(lr) for lr in (r.metric("learning_rate") for r in done) if math.isfinite(lr)})
    if final_rates:
        models = [f"{m}, final learning rate {'/'.join(final_rates)}" for m in models]
    return (f"{'/'.join(f'{s:,}' for s in steps)} steps of a GNS with {' / '.join(models)}, {fmt(wall)} s, "
            f"{'; '.join(hardware)}, data tier {'/'.join(tiers)}, rollouts of {fmt(horizon)} steps")


# The paper's numbers come from the release's metrics (train.py), so ours are logged the same way.
DEFINITIONS = ("One-step and rollout MSE are the release's (learning_to_simulate/train.py): means over every "
               "particle, kinematic ones included, and for the rollout over sequence_length - 6 steps; MLflow "
               "also holds `one_step_mse_moving` and `rollout_mse_moving` without kinematic particles. ")


def budget_statement(rows: list[RunRow]) -> str:
    """The plain-words explanation of gaps to the paper: how far our training budget is from its 20M steps."""
    done = [r for r in rows if r.ok]
    paper = paper_training_steps()
    if not done:
        return "No finished run: nothing to compare with the paper yet."
    steps = max(int(float(r.param("train.steps", "0"))) for r in done)
    fraction = steps / paper
    text = (f"Budget: at most {steps:,} training steps per run, {100 * fraction:.2g}% of the paper's {paper:,} "
            f"(batch 2). ")
    if fraction < 0.01:
        text += ("That is far below the paper's budget, so gaps to its figures are expected; a number at or "
                 "below the paper's is on our own, smaller test set (like scenes, not its trajectories) and does "
                 "not show that its accuracy is reproduced. ")
    elif fraction < 1:
        text += "Remaining gaps to the paper are expected from the shorter training and smaller datasets. "
    capped = sorted({r.param("eval.rollout_steps") for r in done} - {"", "None"}, key=float)
    if capped:
        text += (f"Rollouts are cut at `eval.rollout_steps` = {'/'.join(capped)} steps, where the paper rolls out "
                 "whole trajectories (K = 150 to 2000 steps): errors grow along a rollout, so these rollout MSEs "
                 "are not comparable with the paper's (they typically sit below them). ")
    stopped = [r for r in done if r.metric("rollout_stopped") > 0]
    if stopped:
        text += (f"In {len(stopped)} of {len(done)} runs a health monitor stopped some rollouts early (MLflow tag "
                 f"`<split>/rollouts_stopped` says where and why: {', '.join(f'`{r.run_id}`' for r in stopped)}); "
                 "their rollout MSE covers only the steps before the stop. ")
    flagged = [r for r in done if r.metric("rollout_flagged") > 0]
    if flagged:
        text += (f"In {len(flagged)} of {len(done)} runs a monitor outside `eval.stop_on` flagged some rollouts "
                 "(by default: a particle out of the bounds) and they ran on, as the paper's do: the rollout MSE "
                 "counts that error (MLflow tag `<split>/rollouts_flagged` says where: "
                 f"{', '.join(f'`{r.run_id}`' for r in flagged)}). ")
    against_cv = [r.metric("rollout_mse") / comparable_cv(r) for r in done if comparable_cv(r) > 0]
    against_cv = [x for x in against_cv if math.isfinite(x)]
    left_out = sum(r.metric("rollout_stopped") > 0 and not math.isfinite(comparable_cv(r)) for r in done)
    if against_cv:
        low, high = min(against_cv), max(against_cv)
        span = f"{low:.2g}x" + (f" to {high:.2g}x" if high > low else "")
        text += (f"On the same trajectories and steps, the GNS's rollout MSE is {span} that of a "
                 "constant-velocity extrapolation (below 1x: the model beats it"
                 + (f"; left out: {left_out} run(s) with stopped rollouts, evaluated before the baseline over "
                    "the same steps was logged" if left_out else "") + "). ")
    text += DEFINITIONS
    legacy = [r for r in done if not math.isfinite(r.metric("rollout_mse_moving"))]
    if legacy:
        text += (f"{len(legacy)} of {len(done)} runs were evaluated before issue #17 "
                 f"({', '.join(f'`{r.run_id}`' for r in legacy)}): their MSEs leave kinematic particles out and "
                 "their rollout MSE covers one step more (it reads higher by up to N_all / N_moving on domains with "
                 "obstacles), and their model summed the updated edges (`model.aggregate = \"updated_edges\"`). ")
    tiers = sorted({r.tag("dataset_tier") or r.param("sweep.dataset_tier") for r in done})
    if any(t != "paper" for t in tiers):
        text += f"Datasets are the '{'/'.join(tiers)}' tier (fewer and shorter trajectories than the paper's). "
    if any(r.tag("dataset_tier") for r in done):  # set by gns-bench's generators; imported datasets have none
        text += ("The ground truth comes from gns-bench's own solvers (`datasets/<domain>.toml`), in the paper's "
                 "format and units but not its trajectories: the paper's numbers are a reference on like scenes, "
                 "not on the same test set. ")
    return text


# ----------------------------------------------------------------------------------------------
# Domain table (Knowl 5)
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
    baseline = "—" if not math.isfinite(constant_velocity) else f"{fmt(constant_velocity)} ({_against_cv(rows)})"
    stopped = any(r.metric("rollout_stopped") > 0 for r in rows)  # NaN for runs that did not finish
    cells = [ref.name if ref else sweep.domain, ref.simulator if ref else "—", str(ref.dim) if ref else "—",
             f"{ref.max_particles:,}" if ref else "—", str(ref.sequence_length) if ref else "—",
             fmt(one_step), fmt(ref.one_step_mse) if ref else "—", ratio(one_step, ref.one_step_mse if ref else None),
             fmt(rollout), fmt(ref.rollout_mse) if ref else "—",
             ratio(rollout, ref.rollout_mse if ref else None) + (" (stopped rollouts)" if stopped and ref else ""),
             baseline,
             fmt(ref.cconv_rollout_mse) if ref and ref.cconv_rollout_mse else "—",
             *(fmt(mean_std([r.metric(m) for r in rows])[0]) for m in ("ot", "mmd", "kinetic_energy_error")),
             budget(rows), _status_cell(rows), _run_ids(rows)]
    if not any(r.ok for r in rows):
        cells[5] = cells[8] = MISSING
    return "| " + " | ".join(cells) + " |"


def domain_table(collected: list[tuple[SweepSpec, list[RunRow]]]) -> list[str]:
    lines = [DOMAIN_HEADER, "|" + "---|" * DOMAIN_HEADER.count(" | ") + "---|"]
    lines += [domain_row(sweep, rows) for sweep, rows in collected]
    return lines


def inference_section(collected: list[tuple[SweepSpec, list[RunRow]]]) -> list[str]:
    lines = ["## Rollout time per step (App. C.6; Knowl 9)", "",
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
        lines.append("")
    return lines


def runs_table(sweep: SweepSpec, rows: list[RunRow]) -> list[str]:
    header = ["run", *[a.split(".")[-1] for a in sweep.axes], "seed", "status", "MLflow run id", *METRICS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        cells = [r.planned.name, *[axis_value_label(r.planned.axes[a]) for a in sweep.axes], str(r.planned.seed),
                 "ok" if r.ok else f"**{r.status}**", run_id_cell(r),
                 *(fmt(r.metric(m)) for m in METRICS)]
        lines.append("| " + " | ".join(cells) + " |")
    settings = sorted({distribution_settings(r) for r in rows if r.ok})
    lines += ["", "OT: exact EMD (squared Euclidean cost, POT) up to `eval.ot_exact_max_particles` moving particles, "
              "Sinkhorn divergence with `eval.sinkhorn_reg` beyond (the `ot_exact` metric is the fraction of "
              "trajectories evaluated exactly); MMD: Gaussian kernel of width `eval.mmd_bandwidth_radii` x R; both "
              "averaged over `eval.distribution_steps` evenly spaced rollout steps.",
              "", *(f"- {setting}" for setting in settings)]
    return lines


def distribution_settings(row: RunRow) -> str:
    """How a run's OT and MMD were computed, from its logged params and its `ot_exact` metric."""
    exact = row.metric("ot_exact")
    method = ("exact EMD" if exact == 1 else "Sinkhorn divergence" if exact == 0 else
              "—" if not math.isfinite(exact) else f"exact EMD on {exact:.0%} of trajectories, Sinkhorn on the rest")
    return (f"OT method: {method} (exact up to {row.param('eval.ot_exact_max_particles', '?')} particles, "
            f"sinkhorn_reg {row.param('eval.sinkhorn_reg', '?')}); MMD bandwidth "
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


def load_rollouts(run_id: str, artifact_path: str, workdir: Path) -> list[RolloutResult]:
    """The rollouts (with their ground truth) a run logged as an npz artifact; none when it has no such file."""
    local = tracking.download_artifacts(run_id, artifact_path, workdir)
    if local is None:
        return []
    with np.load(local) as data:
        keys = sorted({k.split("/")[0] for k in data.files})
        return [RolloutResult(data[f"{k}/predicted"], data[f"{k}/ground_truth"], data[f"{k}/initial_window"],
                              data[f"{k}/particle_type"],
                              birth_step=data[f"{k}/birth_step"] if f"{k}/birth_step" in data.files else None)
                for k in keys]


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
    rows = collect(sweep, tier) if rows is None else rows
    kind = "stress" if sweep.name.startswith("stress-") else "domain" if not sweep.axes else "ablation"
    lines = [f"# {sweep.name} ({tier} tier)", "", f"{sweep.description}. Domain `{sweep.domain}`; paper: "
             f"{sweep.paper_figure or '—'}. MLflow experiment `{sweep.experiment}`; {len(rows)} planned runs, "
             f"{sum(r.ok for r in rows)} finished.", "", budget_statement(rows), ""]
    if kind == "stress":
        from gns_bench.report.stability import sweep_section

        lines += sweep_section(sweep, rows, out_dir)
    elif kind == "domain":
        lines += ["## Against the paper (App. C.4; Knowl 5)", "", *domain_table([(sweep, rows)]), ""]
    else:
        lines += ablation_section(sweep, rows, out_dir)
    lines += ["## Runs", "", *runs_table(sweep, rows), "", *time_section(rows, out_dir),
              *rollout_section(rows, out_dir)]
    return _write(out_dir, lines)


def write_domains_report(sweeps: list[SweepSpec], tier: str, out_dir: Path) -> Path:
    """The paper's domain table across domain sweeps, ours beside it, one row per sweep (missing ones too)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    collected = [(s, collect(s, tier)) for s in sweeps]
    every = [r for _, rows in collected for r in rows]
    lines = [f"# Domains ({tier} tier)", "",
             "The paper's results on its 16 domains (App. C.4; Knowl 5 of the summary in `../shared/paper/`) "
             "with our numbers beside them: mean over seeds of the test-split metrics, MSEs absolute (not "
             "x1e-9 / x1e-3); ratio = ours / paper. CConv: the paper's best CConv baseline (Sec. 5.5 and "
             "App. D.1; Knowl 8, approximate). Each row states its budget. Per-domain runs "
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
        from gns_bench.report.stability import write_stability_report

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
        rows = collect(spec, tier)
        if any(row.record for row in rows):
            written.append(write_sweep_report(spec, tier, reports_root / spec.name / tier, rows))
    from gns_bench.report.stability import write_stability_report

    written.append(write_domains_report(domain_sweeps(), tier, reports_root / "domains" / tier))
    written.append(write_stability_report(tier, reports_root / "stability" / tier))
    return written
