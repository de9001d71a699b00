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

from gns_bench import simulators, tracking
from gns_bench.data.format import RIGID_PARTICLE_TYPE
from gns_bench.evaluate import metrics
from gns_bench.evaluate import registry as metric_registry
from gns_bench.evaluate.plots import flag_marks
from gns_bench.report import baselines, figures
from gns_bench.report.baselines import write_baselines_report
from gns_bench.report.cells import (
    DIAGNOSTIC_COLUMNS,
    MISSING,
    against_cv,
    any_stopped,
    budget_statement,
    cv_ratio,
    definitions_section,
    fmt,
    machines,
    mean_cell,
    ratio,
    relative_to_cv,
    run_id_cell,
    run_ids_cell,
    shared_cores_mark,
    status_cell,
    steps_covered,
    times,
    used_precision,
)
from gns_bench.report.collect import (
    METRICS,
    RunRow,
    axis_value_label,
    collect,
    domain_sweeps,
    load_rollouts,
    mean_std,
    resolve_sweep,
    unfinished_records,
)
from gns_bench.report.index import write_index
from gns_bench.report.kept import KEPT_FILE, UNFINISHED, read_kept, write_kept
from gns_bench.report.reference import ablation_reference, display_name, domain_reference, inference_reference
from gns_bench.report.stability import sweep_section, write_stability_report
from gns_bench.report.study import candidates_section, gravity_studies_section
from gns_bench.report.verdict import (
    EQUIVALENCE_MARGIN,
    ERROR,
    ONE_STEP,
    STEPS_BEFORE_STOP,
    Arm,
    cpu_kind,
    effect,
    error_measure,
    interval_text,
    judge_axis,
    matched,
)
from gns_bench.sweep.spec import SWEEPS_DIR, SweepSpec, discover_sweeps, load_sweep
from gns_bench.sweep.summaries import SUMMARY_FILE

# ----------------------------------------------------------------------------------------------
# Domain table (Table 1, App. C.4)
# ----------------------------------------------------------------------------------------------

ACCURACY_HEADER = ("| domain | simulator | max N | K | one-step MSE | paper | ratio | MSE, rollout steps 1-10 "
                   "| rollout MSE | paper | ratio | GNS / constant velocity | seeds |")
DISTRIBUTION_HEADER = "| domain | OT | MMD | KE error | rollout steps covered |"
DIAGNOSTICS_HEADER = "| domain | " + " | ".join(title for _, title in DIAGNOSTIC_COLUMNS) + " |"
DIAGNOSTICS_NOTE = (
    "Gravity ratio: over the particles the ground truth has in free fall (true acceleration g within 10% on three "
    "frames in a row: blocks before their first contact), the mean predicted acceleration along g over the "
    "true one; 1 = gravity learned, 0 = a block that hovers. *One step*: the model on true windows; *held "
    "still*: the same windows with every frame set to the last (all input velocities 0, a block at rest in "
    "mid-air let go: a state training windows rarely or never show, and the one a rollout that stops a block in "
    "mid-air reaches; near 0, the model never leaves it); *held still, fall over 10 steps*: a frame where all the "
    "material is in free fall, held still and let go, rolled out 10 steps by the model, its fall along g over "
    "the fall at g (the steps after the release count too, where a model may push the material back up); "
    "*rollout*: along its own rollout. Floor's push: over the particles landing in the truth (moving towards "
    "the floor within 3 R of it, faster than five frames of free fall give), the predicted push beyond gravity "
    "over the true one, the model on true windows; near 0, landing material falls on through the floor. "
    "Centre-of-mass fall: "
    "how far the moving particles' centre moved along g by the "
    "rollout's last step, over the truth's (where the truth's moved at least R). Particles through a wall: the "
    "share of moving particles outside the bounds at some step. Steps before a trip: the first step a health "
    "monitor stopped or flagged the rollout, or its length. Mean over test trajectories and seeds; '—': the run "
    "was evaluated before these diagnostics existed, or none of its particles was in free fall "
    "(`gns_bench/evaluate/diagnostics.py`).")
BUDGET_HEADER = ("| domain | training steps | precision | training time (min) | hardware | data tier | status "
                 "| MLflow runs |")


def _table(header: str, rows: list[list[str]]) -> list[str]:
    return [header, "|" + "---|" * header.count(" | ") + "---|", *("| " + " | ".join(r) + " |" for r in rows)]


def accuracy_row(sweep: SweepSpec, rows: list[RunRow], compare: bool) -> list[str]:
    """Shaped like the paper's Table 1; `compare` False (smoke) prints no ratio and no baseline."""
    ref = domain_reference(sweep.domain)
    one_step = mean_std([r.metric("one_step_mse") for r in rows])[0]
    rollout, _, seeds = mean_std([r.metric("rollout_mse") for r in rows])
    stopped = any_stopped(rows)
    done = any(r.ok for r in rows)
    early = mean_std([r.metric("mse_h10") for r in rows])[0]
    covered = mean_std([r.metric("rollout_steps") for r in rows])[0]
    # Like for like with the paper's whole-rollout MSE only where no rollout was stopped; a stopped one's MSE
    # covers fewer steps (shown with how many), and no ratio is drawn from it.
    whole = ratio(rollout, ref.rollout_mse if ref else None) if not stopped else "— (rollouts stopped)"
    return [display_name(sweep.domain), ref.simulator if ref else "—",
            f"{ref.max_particles:,}" if ref else "—", str(ref.sequence_length) if ref else "—",
            fmt(one_step) if done else MISSING, fmt(ref.one_step_mse) if ref else "—",
            ratio(one_step, ref.one_step_mse if ref else None) if compare else "—",
            fmt(early) if done else MISSING,
            (fmt(rollout) + (f" (over {covered:.0f} steps, mean)" if stopped else "")) if done else MISSING,
            fmt(ref.rollout_mse) if ref else "—", whole if compare else "—",
            against_cv(rows) if compare else "—", str(seeds)]


def distribution_row(sweep: SweepSpec, rows: list[RunRow]) -> list[str]:
    return [display_name(sweep.domain),
            *(fmt(mean_std([r.metric(m) for r in rows])[0]) for m in ("ot", "mmd", "kinetic_energy_error")),
            steps_covered(rows)]


def diagnostics_row(sweep: SweepSpec, rows: list[RunRow]) -> list[str]:
    def mean(metric: str) -> str:
        return fmt(mean_std([r.metric(metric) for r in rows if r.ok])[0])

    return [display_name(sweep.domain), *(mean(name) for name, _ in DIAGNOSTIC_COLUMNS)]


def budget_row(sweep: SweepSpec, rows: list[RunRow]) -> list[str]:
    done = [r for r in rows if r.ok]
    steps = sorted({int(r.metric("train/final_step")) for r in done if math.isfinite(r.metric("train/final_step"))})
    wall = mean_std([r.metric("train/wall_time_s") for r in done])[0]
    return [display_name(sweep.domain), "/".join(f"{s:,}" for s in steps) or "—",
            "/".join(sorted({used_precision(r) for r in done})) or "—",
            fmt(wall / 60) + shared_cores_mark(done),
            machines(done) or "—",
            "/".join(sorted({r.tag("dataset_tier") or r.param("sweep.dataset_tier") for r in done})) or "—",
            status_cell(rows), run_ids_cell(rows)]


def domain_tables(collected: list[tuple[SweepSpec, list[RunRow]]], compare: bool) -> list[str]:
    """The accuracy table (Table 1's shape), then the distributional metrics, then what each row cost."""
    return ["## Against the paper (Table 1, App. C.4)", "",
            *_table(ACCURACY_HEADER, [accuracy_row(s, rows, compare) for s, rows in collected]), "",
            "## Distributional metrics (App. B.4)", "",
            *_table(DISTRIBUTION_HEADER, [distribution_row(s, rows) for s, rows in collected]), "",
            "## Physical diagnostics", "",
            *_table(DIAGNOSTICS_HEADER, [diagnostics_row(s, rows) for s, rows in collected]), "", DIAGNOSTICS_NOTE, "",
            "## Budget", "", *_table(BUDGET_HEADER, [budget_row(s, rows) for s, rows in collected]), ""]


def inference_section(collected: list[tuple[SweepSpec, list[RunRow]]]) -> list[str]:
    lines = ["## Rollout time per step (App. C.6)", "",
             "| domain | ours (s/step) | hardware | paper GNS (s/step, V100) | paper solver (s/step, CPU) |",
             "|---|---|---|---|---|"]
    for sweep, rows in collected:
        ref = domain_reference(sweep.domain)
        paper = inference_reference(ref.dim, ref.simulator) if ref else None
        ours = mean_std([r.metric("rollout_seconds_per_step") for r in rows])[0]
        hardware = machines([r for r in rows if r.ok]) or "—"
        ours_cell = fmt(ours) if any(r.ok for r in rows) else MISSING
        gns, solver = ((f"{paper[k][0]:g}-{paper[k][1]:g}" for k in ("gns_seconds", "solver_seconds")) if paper
                       else ("—", "—"))
        lines.append(f"| {display_name(sweep.domain)} | {ours_cell} | {hardware} | {gns} | {solver} |")
    return lines + ["", "The paper's times are per step on a V100 (GNS) and a 6-core CPU (solver), ranges over its "
                        "domains of that kind; ours are on the hardware listed, at our model and dataset size."]


# ----------------------------------------------------------------------------------------------
# Ablations (Sec. 5.4, Fig. 4; App. C.1)
# ----------------------------------------------------------------------------------------------

def ablation_stats(axis: str, values: list, rows: list[RunRow], like_for_like: bool) -> dict[str, list]:
    """(mean, sample std, seeds) of each panel's measure at each value of the axis, in the figure's order: the
    metrics of `figures.PANELS`, and with `like_for_like` (a monitor stopped rollouts, so the raw rollout MSE
    covers different steps in different runs) `figures.STOPPED_PANELS` after the rollout MSE: each run's rollout
    MSE over constant velocity's on the same steps, and its rollout steps before the stop."""
    def measure(row: RunRow, metric: str) -> float:
        return relative_to_cv(row) if metric == "vs_cv" else row.metric(metric)

    return {m: [mean_std([measure(r, m) for r in rows if r.planned.axes[axis] == v]) for v in values]
            for m, _ in figures.ablation_panels(like_for_like)}


def against_default(axis: str, values: list, rows: list[RunRow], reference: dict) -> dict[int, str]:
    """Per axis value (its index in `values`), the verdict's error measure against the default's, as the verdict
    computes it: ratio of geometric means over seeds with its 95% interval."""
    metric, _ = error_measure(rows)
    done = [r for r in rows if r.ok]
    if not metric or "default" not in reference:
        return {}

    def arm(value) -> Arm:
        at = [r for r in done if r.planned.axes[axis] == value]
        return Arm.of([r.metric(metric) for r in at], [cpu_kind(r) for r in at])

    defaults = [i for i, v in enumerate(values) if axis_value_label(v) == axis_value_label(reference["default"])]
    if not defaults:
        return {}
    base = arm(values[defaults[0]])
    out = {defaults[0]: "1 (the default)"}
    for i, value in enumerate(values):
        if i == defaults[0]:
            continue
        a, b, _ = matched(arm(value), base)
        out[i] = interval_text(effect(a, b)[0]) if a and b else "—"
    return out


def ablation_section(sweep: SweepSpec, rows: list[RunRow], out_dir: Path, compare: bool = True) -> list[str]:
    lines = []
    for axis in sweep.axes:
        values = list(dict.fromkeys(r.planned.axes[axis] for r in rows))
        stats = ablation_stats(axis, values, rows, like_for_like=compare and any_stopped(rows))
        reference = ablation_reference(axis)
        name = axis.split(".")[-1]
        figure = figures.ablation_figure(axis, values, stats, reference, out_dir / f"ablation_{name}.png")
        default = axis_value_label(reference["default"]) if "default" in reference else "none given"
        lines += [f"## {axis}", "", f"Paper default: {default} (dashed line); x scale: {reference['scale']}; "
                  "error bars: sample std over seeds (n - 1).", "", f"![{axis}]({figure.name})", ""]
        if any_stopped(rows):
            lines += ["A health monitor stopped some rollouts, so rollout MSE, OT and MMD cover different steps in "
                      "different runs (column *rollout steps*). *vs constant velocity* divides the rollout MSE by "
                      "constant velocity's over the same steps: that column compares runs like for like"
                      + (", and so do the figure's panels *vs constant velocity, same steps* (there the mean over "
                         "seeds of each run's ratio; in the table the ratio of the means) and *rollout steps before "
                         "a stop*." if compare else "."), ""]
        judged = compare and sweep.kind == "ablation"  # the paper's findings are about the GNS's own axes
        against = against_default(axis, values, rows, reference) if judged else {}
        lines += ["| value | seeds | one-step MSE | rollout MSE | OT | MMD | rollout steps | vs constant velocity "
                  "| vs the default (the verdict's measure) |", "|---|---|---|---|---|---|---|---|---|"]
        for i, value in enumerate(values):
            at_value = [r for r in rows if r.planned.axes[axis] == value]
            seeds = stats["rollout_mse"][i][2]
            cells = [mean_cell(*stats[m][i]) for m, _ in figures.PANELS]
            cells += [steps_covered(at_value), (cv_ratio(at_value) if seeds else MISSING) if compare else "—",
                      against.get(i, "—")]
            lines.append(f"| {axis_value_label(value)} | {seeds}/{len(at_value)} | " + " | ".join(cells) + " |")
        if against:
            lines += ["", f"*vs the default*: {error_measure(rows)[1] or 'no common horizon'}, geometric mean over "
                      "seeds against the default's, with its 95% interval, runs on the default's CPU kinds only "
                      "(`gns_bench/report/verdict.py`): the number the verdict below judges."]
        finding = "better" in reference or bool(reference.get("no_effect"))
        rules = ["", VERDICT_RULES] if finding else []  # how every verdict above was drawn
        lines += ["", *verdict_lines(axis, rows, reference), *rules, ""] if judged else [""]
    return lines


def baseline_section(sweep: SweepSpec, tier: str, rows: list[RunRow], reports_root: Path, compare: bool) -> list[str]:
    """A baseline beside the GNS on the same domain and tier (the domain sweep's runs), ours and the paper's
    (Sec. 5.5, App. D.1): the baselines report's row for this sweep (`report/baselines.py`: the raw ratio and,
    like for like, each model against constant velocity over its own steps) and its verdict."""
    architecture = simulators.display_name(baselines.architecture_of(sweep))
    domain = next((s for s in domain_sweeps() if s.domain == sweep.domain), None)
    gns_rows = collect(domain, tier, reports_root) if domain else []
    lines = [f"## {architecture} beside the GNS (Sec. 5.5)", "",
             f"The GNS is the domain sweep's run at this tier ({_link_report(domain.name if domain else '?', tier)}); "
             f"{architecture}'s value is its best run here (lowest error against constant velocity over the same "
             "steps), as the paper reports CConv's best over its sweeps (read off the paper's bar chart: "
             f"approximate). All baselines side by side: {_link_report('baselines', tier)}.", "",
             *_table(baselines.HEADER, [baselines.comparison_row(sweep, rows, gns_rows, compare)]), ""]
    if compare:
        lines += [baselines.VERDICT_RULE, "", baselines.verdict_line(sweep, rows, gns_rows), ""]
    return lines


def _link_report(name: str, tier: str) -> str:
    return f"[{name}/{tier}](../../{name}/{tier}/README.md)"


VERDICT_RULES = ("*How the verdicts are drawn* (`gns_bench/report/verdict.py`): each comparison is the ratio of "
                 "geometric means over seeds with its 95% t interval on the log errors (Welch's, or pooled when an "
                 "arm has one seed); a direction is *reproduced* when the interval lies wholly on the paper's side "
                 "of 1, *contradicted* when wholly on the other, else *inconclusive*. A finding of little difference "
                 f"is *reproduced* only by an equivalence test (90% interval within {EQUIVALENCE_MARGIN}x either "
                 "way, at least two seeds a side). Only runs on the same CPU kind are compared.")


def verdict_lines(axis: str, rows: list[RunRow], reference: dict) -> list[str]:
    """The computed verdicts on the paper's finding for this axis (gns_bench/report/verdict.py): on the error;
    where a health monitor stopped rollouts, on how many steps they ran before the stop; and where the paper
    states a direction for it, on the one-step error."""
    if "better" not in reference and not reference.get("no_effect"):
        return [f"**Verdict ({axis}):** the paper states no finding on this axis to compare with."]
    verdicts = judge_axis(axis, rows, reference)
    error, length, one_step = (verdicts.get(q) for q in (ERROR, STEPS_BEFORE_STOP, ONE_STEP))
    finished = sum(r.ok for r in rows)
    so_far = "" if finished == len(rows) else (f" So far: from {finished} of the {len(rows)} planned runs; the rest "
                                                "are not finished, and the verdict may change with them.")
    lines = [f"**Verdict ({axis}): {error.verdict}.** Paper: {reference.get('summary', '—')}. Ours: {error.detail}."
             + so_far]
    if length:
        lines += ["", f"**Verdict on rollout length ({axis}): {length.verdict}.** The error above is taken over steps "
                      "every rollout reached, so it cannot see a model whose rollouts collapse sooner; this one "
                      f"compares the mean number of steps they ran (column *rollout steps*). Ours: {length.detail}."
                      + so_far]
    if one_step:
        lines += ["", f"**Verdict on the one-step error ({axis}): {one_step.verdict}.** Paper (Sec. 5.4, Fig. 4's "
                      f"upper row): {reference.get('one_step_summary', '—')}. Ours: {one_step.detail}; one-step MSE "
                      "on the test trajectories' uncorrupted inputs (column *one-step MSE*)." + so_far]
    return lines


def runs_table(sweep: SweepSpec, rows: list[RunRow]) -> list[str]:
    shown = [*METRICS, *(m.name for m in metric_registry.registered())]  # the registered ones after the paper's
    header = ["run", *[a.split(".")[-1] for a in sweep.axes], "seed", "status", "MLflow run id", *shown]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        cells = [r.planned.name, *[axis_value_label(r.planned.axes[a]) for a in sweep.axes], str(r.planned.seed),
                 "ok" if r.ok else f"**{r.status}**", run_id_cell(r),
                 *(fmt(r.metric(m)) for m in shown)]
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


def rollout_section(rows: list[RunRow], out_dir: Path, previous: dict | None = None) -> tuple[list[str], dict]:
    """Best and worst test trajectories of the run with the lowest rollout MSE, as PNG and GIF (once when they
    are the same trajectory), with a note naming the best run like for like when that is another
    (`_fairer_pick`). Returns the lines and the picks (run, trajectories, their errors), which the run summary
    keeps: when the run's rollouts are no longer in MLflow, the committed pictures are shown again."""
    done = sorted((r for r in rows if r.ok and math.isfinite(r.metric("rollout_mse"))),
                  key=lambda r: r.metric("rollout_mse"))
    lines = ["## Rollouts", ""]
    if not done:
        return lines + ["No finished run with rollouts.", ""], {}
    row = done[0]
    model = simulators.display_name(row.planned.config.model.architecture)
    linked = _shared_pictures(row, out_dir)
    if linked:  # another report already draws this run's rollouts: link them, do not copy them
        for stale in [*out_dir.glob("rollout_*.png"), *out_dir.glob("rollout_*.gif"), out_dir / "rigidity.png"]:
            stale.unlink(missing_ok=True)  # drawn here by an earlier report of this sweep
        return lines + linked + _fairer_pick(row, done), {}
    with tempfile.TemporaryDirectory() as tmp:
        loaded = load_rollouts(row.artifact_run_id, f"evaluation/{row.split}_rollouts.npz", Path(tmp))
    results = {i: r for i, r in enumerate(loaded) if r.predicted.shape[0]}  # trajectory number -> rollout
    if results:
        errors = {i: metrics.rollout_mse(r.predicted, r.ground_truth[: r.predicted.shape[0]], r.scored_mask())
                  for i, r in results.items()}
        chosen = dict.fromkeys([min(errors, key=errors.get), max(errors, key=errors.get)])  # one when they agree
        picks = {"run_id": row.run_id, "source_run": row.tag("shared_from") or row.run_id, "split": row.split,
                 "rigidity": False, "shown": [
            {"label": "best" if i == 0 else "worst", "trajectory": index, "mse": float(errors[index]),
             "steps": int(results[index].predicted.shape[0]), "stopped": results[index].stop_reason or ""}
            for i, index in enumerate(chosen)]}
        if _drawn_before(picks, previous, out_dir):  # a report written again: the same run's same rollouts
            return _rollout_lines(lines, row, done, model, previous), previous
        alone = len(picks["shown"]) == 1
        flagged = flag_marks(row.tag(f"{row.split}/rollouts_flagged"))
        for shown in picks["shown"]:
            result, name = results[shown["trajectory"]], shown["label"]
            marks = flagged.get(shown["trajectory"], {})
            title = _rollout_title(shown, alone)
            figures.rollout_png(result, out_dir / f"rollout_{name}.png", title, marks=marks, model=model)
            figures.rollout_gif(result, out_dir / f"rollout_{name}.gif", title, marks=marks, model=model)
        # rigid materials (BOXBATH's cube): how far each body's shape drifts, the model against ground truth
        picks["rigidity"] = figures.rigidity_figure(loaded, RIGID_PARTICLE_TYPE, out_dir / "rigidity.png",
                                                    model=model) is not None
    elif previous and previous.get("run_id") == row.run_id and all(
            (out_dir / f"rollout_{s['label']}.png").is_file() for s in previous.get("shown", [])):
        picks = previous  # the store that held the rollouts is gone; the committed pictures stand
    else:
        return lines + [f"Run {run_id_cell(row)} logged no rollouts.", ""], {}
    return _rollout_lines(lines, row, done, model, picks), picks


def _drawn_before(picks: dict, previous: dict | None, out_dir: Path) -> bool:
    """Whether the pictures in `out_dir` show `picks` already: the last report drew the same trajectories of the
    same run (their errors and stops the same) and every file it drew is there. Drawing them takes seconds a
    report, and a campaign rewrites every report each time a sweep finishes."""
    def chosen(p: dict) -> dict:  # the picture of rigidity is drawn whenever the rollouts hold a rigid body
        return {k: v for k, v in p.items() if k != "rigidity"}

    if not previous or chosen(previous) != chosen(picks):
        return False
    files = [f"rollout_{s['label']}.{ext}" for s in previous["shown"] for ext in ("png", "gif")]
    return all((out_dir / name).is_file() for name in files + (["rigidity.png"] if previous.get("rigidity") else []))


def _rollout_lines(lines: list[str], row: RunRow, done: list[RunRow], model: str, picks: dict) -> list[str]:
    """`lines` and the section's text: which run's rollouts `picks` shows, and the pictures' links."""
    lines = lines + [f"From run {run_id_cell(row)} ({row.planned.name}, lowest rollout MSE), split '{picks['split']}': "
              f"ground truth beside {'the GNS' if model == 'GNS' else model} on one frame; the MSE is of moving "
              "particles over the steps shown.", "", *_fairer_pick(row, done)]
    for shown in picks["shown"]:
        name = shown["label"]
        lines += [f"**{_rollout_title(shown, len(picks['shown']) == 1)}**", "",
                  f"![{name} rollout](rollout_{name}.png)", "", f"![{name} animation](rollout_{name}.gif)", ""]
    if picks.get("rigidity"):
        lines += ["### Rigidity", "", f"Rigid-body drift of every test rollout ({figures.RIGIDITY_WORDS}).", "",
                  "![rigid-body drift](rigidity.png)", ""]
    return lines


def _fairer_pick(shown: RunRow, done: list[RunRow]) -> list[str]:
    """A warning when the run drawn (lowest raw rollout MSE) is not the lowest against constant velocity over the
    same steps: a run whose rollouts a monitor stopped early has a raw MSE over few steps, which reads low, so
    the picture is then not of the run the verdicts and the baselines report would call best."""
    fair = baselines.best_run(done)  # lowest against constant velocity over the same steps
    if fair is None or fair is shown or not math.isfinite(relative_to_cv(shown)):
        return []
    return [f"Like for like this is not the best run: against constant velocity over the same steps it reaches "
            f"{times(relative_to_cv(shown))} where {fair.planned.name} ({run_id_cell(fair)}) reaches "
            f"{times(relative_to_cv(fair))}; their rollouts covered {fmt(shown.metric('rollout_steps'))} and "
            f"{fmt(fair.metric('rollout_steps'))} steps before any monitor's stop (mean over the test rollouts).", ""]


def _shared_pictures(row: RunRow, out_dir: Path) -> list[str]:
    """Links to the rollout pictures another report (same tier) already drew of `row`'s training run, when
    `row` is a copy of a run another sweep trained, or is the run other copies were made from: the report of
    the sweep that trained it, else any other (domain reports are written first); none otherwise."""
    source_run = row.tag("shared_from") or row.run_id
    source = row.tag("shared_from_run")
    tier_dir = out_dir.name
    reports_root = out_dir.parent.parent
    candidates = [reports_root / source.split("/")[0] / tier_dir] if "/" in source else []
    candidates += sorted({p.parent for name in (KEPT_FILE, SUMMARY_FILE)
                          for p in reports_root.glob(f"*/{tier_dir}/{name}")})
    for source_dir in candidates:
        if source_dir.resolve() == out_dir.resolve():
            continue
        picks = read_kept(source_dir).get("rollouts") or {}
        drew = picks.get("source_run", picks.get("run_id"))
        if drew != source_run or not picks.get("shown") or not all(
                (source_dir / f"rollout_{s['label']}.png").is_file() for s in picks["shown"]):
            continue
        relative = f"../../{source_dir.parent.name}/{source_dir.name}"
        trained = f"which {source.split('/')[0]} trained" if "/" in source else "trained by this sweep"
        lines = [f"The lowest rollout MSE is run {run_id_cell(row)}, {trained}; its pictures are in "
                 f"[{source_dir.parent.name}/{source_dir.name}]({relative}/README.md):", ""]
        for shown in picks["shown"]:
            name = shown["label"]
            lines += [f"**{_rollout_title(shown, len(picks['shown']) == 1)}**", "",
                      f"![{name} rollout]({relative}/rollout_{name}.png)", ""]
        return lines
    return []


def _rollout_title(shown: dict, alone: bool = False) -> str:
    label = "best and worst" if alone else shown["label"]
    stop = f", stopped at step {shown['steps']}: {shown['stopped']}" if shown.get("stopped") else ""
    return f"{label}: trajectory {shown['trajectory']}, MSE {shown['mse']:.3g} over {shown['steps']} steps{stop}"


def previous_picks(report_dir: Path) -> dict | None:
    """The rollout pictures the last report at `report_dir` showed (what it kept), if any."""
    return read_kept(report_dir).get("rollouts")


# ----------------------------------------------------------------------------------------------
# Entry points
# ----------------------------------------------------------------------------------------------

def _write(out_dir: Path, lines: list[str]) -> Path:
    path = out_dir / "README.md"
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path


def write_sweep_report(sweep: SweepSpec, tier: str, out_dir: Path, rows: list[RunRow] | None = None) -> Path:
    """The sweep's report from `rows` (its collected runs; collected here when not given), and what it keeps of
    the runs' artifacts (`report/kept.py`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = collect(sweep, tier, out_dir.parent.parent) if rows is None else rows
    compare = tier != "smoke"
    lines = [f"# {sweep.name} ({tier} tier)", "", budget_statement(rows, tier), "",
             f"{sweep.description}. Domain `{sweep.domain}`; paper: {sweep.paper_figure or '—'}. MLflow experiment "
             f"`{sweep.experiment}`; {len(rows)} planned runs, {sum(r.ok for r in rows)} finished.", "",
             *definitions_section()]
    extras: dict = {}
    if sweep.kind == "stress":
        section, stress = sweep_section(sweep, rows, out_dir,
                                        saved=read_kept(out_dir).get("stress"))
        lines += section
        extras = {"stress": stress} if stress else {}
    elif sweep.kind == "domain":
        lines += domain_tables([(sweep, rows)], compare)
        if compare:  # a smoke run is a pipeline check: its studies' curves say nothing about gravity
            lines += gravity_studies_section(sweep.domain, tier, out_dir.parent.parent)
    elif sweep.candidates:
        lines += candidates_section(sweep, tier, rows, out_dir, compare)
    else:
        if sweep.kind == "baseline":
            lines += baseline_section(sweep, tier, rows, out_dir.parent.parent, compare)
        lines += ablation_section(sweep, rows, out_dir, compare)
    rollouts, picks = rollout_section(rows, out_dir, previous_picks(out_dir))
    lines += ["## Runs", "", *runs_table(sweep, rows), "", *time_section(rows, out_dir), *rollouts]
    extras |= {"rollouts": picks} if picks else {}
    extras |= {UNFINISHED: unfinished} if (unfinished := unfinished_records(rows)) else {}
    write_kept(out_dir, sweep.name, tier, extras)
    return _write(out_dir, lines)


def write_domains_report(sweeps: list[SweepSpec], tier: str, out_dir: Path) -> Path:
    """The paper's domain table across domain sweeps, ours beside it, one row per sweep (missing ones too)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    collected = [(s, collect(s, tier, out_dir.parent.parent)) for s in sweeps]
    every = [r for _, rows in collected for r in rows]
    filled = sum(any(r.ok for r in rows) for _, rows in collected)
    lines = [f"# Domains ({tier} tier)", "", budget_statement(every, tier), "",
             f"The paper's 16 domains (Table 1, App. C.4), {filled} of {len(collected)} with a finished run, our "
             "numbers beside the paper's: means over seeds of the test-split metrics, MSEs absolute (not x1e-9 / "
             "x1e-3); ratio = ours / paper. Per-domain runs, time against error and rollouts: "
             f"`reports/domain-<id>/{tier}/` (`gns-bench report domain-<id> --tier {tier}`).", "",
             *definitions_section(), *domain_tables(collected, tier != "smoke"), *inference_section(collected)]
    return _write(out_dir, lines)


def write_report(sweep: str | Path, tier: str = "smoke", reports_root: Path = Path("reports")) -> Path:
    """Write `reports_root/<sweep name>/<tier>/README.md` (+ PNG/GIF) from MLflow; returns the README path.

    `sweep` is a sweep file, a sweep name (`ablation-noise_std`, `domain-goop`), `domains` for the table
    across all domain sweeps, or `stability` for the stress sweeps' report (`write_all_reports` writes them all).
    """
    reports_root = Path(reports_root)
    if str(sweep) == "index":
        return write_index(reports_root)
    if str(sweep) == "baselines":
        return write_baselines_report(tier, reports_root / "baselines" / tier, reports_root)
    if str(sweep) == "domains":
        return write_domains_report(domain_sweeps(), tier, reports_root / "domains" / tier)
    if str(sweep) == "stability":
        return write_stability_report(tier, reports_root / "stability" / tier)
    spec = resolve_sweep(sweep)
    return write_sweep_report(spec, tier, reports_root / spec.name / tier)


def write_all_reports(tier: str = "smoke", reports_root: Path = Path("reports"),
                      sweeps_dir: Path = SWEEPS_DIR) -> list[Path]:
    """The report of every sweep in `sweeps_dir` that has runs at `tier` (domain sweeps first: the others link
    to their pictures of shared runs), then the domain table, the stability and baselines reports (always, gaps
    shown as missing) and the front page. Returns the README paths in that order."""
    written = []
    specs = [load_sweep(path) for path in discover_sweeps(sweeps_dir)]
    with tracking.one_view():  # the same runs are read for many pages
        for spec in sorted(specs, key=lambda sweep: sweep.kind != "domain"):  # domains first: others link to them
            rows = collect(spec, tier, reports_root)
            if any(row.record for row in rows):
                written.append(write_sweep_report(spec, tier, reports_root / spec.name / tier, rows))
        return written + write_overviews(tier, reports_root)


def write_overviews(tier: str, reports_root: Path = Path("reports")) -> list[Path]:
    """The pages that read every sweep of a tier: the domain table, the stability and baselines reports (gaps
    shown as missing), then the front page. A campaign rewrites them after each sweep, so that the committed
    reports agree with each other at any point."""
    with tracking.one_view():  # the same runs are read for many pages
        return [write_domains_report(domain_sweeps(), tier, reports_root / "domains" / tier),
                write_stability_report(tier, reports_root / "stability" / tier),
                write_baselines_report(tier, reports_root / "baselines" / tier, reports_root),
                write_index(reports_root)]
