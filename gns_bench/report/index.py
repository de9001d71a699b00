"""The front page, `reports/README.md`: one row per claim of the paper, where gns-bench stands on it.

Written by `gns-bench report index` (and at the end of `report all`) from the committed run summaries beside
each report (`runs.json`) and MLflow where it still holds the runs, so it is rebuilt the same way on any
machine. Each claim is shown at the most thorough tier that has a finished run (paper, cpu, small; smoke runs
only check the pipeline and are never shown as results), with our figure, the paper's, and a verdict computed
from the numbers, each linking to the report that holds the detail.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from gns_bench import simulators
from gns_bench.config import TIERS
from gns_bench.datasets import resolve_for_domain
from gns_bench.durations import format_duration
from gns_bench.report import baselines
from gns_bench.report.cells import (
    any_stopped,
    comparable_cv,
    fmt,
    machines,
    ratio,
    relative_to_cv,
    run_cpu_generation,
    times,
)
from gns_bench.report.collect import RunRow, collect, domain_sweeps, mean_std
from gns_bench.report.intervals import Interval, mean_interval
from gns_bench.report.kept import read_kept
from gns_bench.report.reference import (
    ablation_reference,
    baseline_rollout_mse,
    display_name,
    domain_reference,
    inference_reference,
)
from gns_bench.report.stability import held_out_interval
from gns_bench.report.verdict import EQUIVALENCE_MARGIN, ERROR, ONE_STEP, judge_axis
from gns_bench.sweep.campaigns import CAMPAIGNS_DIR, load_campaign
from gns_bench.sweep.spec import SWEEPS_DIR, SweepSpec, discover_sweeps, load_sweep

RESULT_TIERS = [t for t in reversed(TIERS) if t != "smoke"]  # most thorough first: what a claim is shown at
MAJOR_AXES = ("message_passing_steps", "connectivity_radius", "noise_std", "processor_sharing",
              "position_encoding", "noise_correction")  # Sec. 5.4 and Fig. 4; the others are App. C.1's
GENERALISATION = (  # (stress sweep, the paper's claim, whether the paper's rollouts stay stable there)
    ("stress-waterramps", "WATERRAMPS: generalises to an arena with inflow, far larger than training (Sec. 5.3)", True),
    ("stress-continuous", "CONTINUOUS: interpolates friction angles held out of training (Sec. 5.3, App. C.5)", True),
    ("stress-multimaterial", "MULTIMATERIAL: handles unseen shapes (Sec. 5.2)", True),
    ("stress-boxbath", "BOXBATH: stays stable over rollouts far longer than training (Sec. 5.3, App. C.7)", True),
    ("stress-boxbath-shake", "FLUIDSHAKE-BOX: the floating box slowly deforms over 1,500 shaken steps "
                             "(App. C.7, a failure mode)", False),
)
HEADER = "| claim (paper) | tier | ours | paper | verdict | report |"
CAMPAIGN_TIERS = ("cpu", "paper")  # the tiers a campaign runs (`small` was the earlier protocol)


def _finished(rows: list[RunRow]) -> bool:
    return any(r.ok for r in rows)


def best_tier(sweep: SweepSpec, reports_root: Path) -> tuple[str, list[RunRow]]:
    """The most thorough tier at which the sweep has a finished run, and its rows ("" when none)."""
    for tier in RESULT_TIERS:
        rows = collect(sweep, tier, reports_root)
        if _finished(rows):
            return tier, rows
    return "", []


def _link(sweep: str, tier: str) -> str:
    return f"[{sweep}/{tier}]({sweep}/{tier}/README.md)" if tier else "—"


def domain_claim(reports_root: Path) -> list[str]:
    """Table 1: how many domains have a result, how their rollout MSE compares with the paper's, and with
    constant velocity on the same steps."""
    rows_by_domain = [(s, *best_tier(s, reports_root)) for s in domain_sweeps()]
    done = [(s, tier, rows) for s, tier, rows in rows_by_domain if tier]
    tiers = sorted({tier for _, tier, _ in done}, key=RESULT_TIERS.index)
    ratios, beats, stopped = [], 0, 0
    for sweep, _, rows in done:
        ref = domain_reference(sweep.domain)
        rollout = mean_std([r.metric("rollout_mse") for r in rows])[0]
        if any_stopped(rows):  # its MSE covers the steps before the stops: nothing to set beside a whole rollout's
            stopped += 1
        elif ref and math.isfinite(rollout):
            ratios.append(rollout / ref.rollout_mse)
        against = [relative_to_cv(r) for r in rows if comparable_cv(r) > 0]  # a diverged seed's NaN counts against
        beats += bool(against) and float(np.mean(against)) < 1
    # Like for like only: the paper's MSEs are over whole rollouts, so only domains whose rollouts all ran whole
    # are set beside them; the others are counted.
    whole = (f"; whole rollouts on {len(ratios)}: rollout MSE {fmt(min(ratios))}x-{fmt(max(ratios))}x the paper's "
             f"(median {fmt(float(np.median(ratios)))}x)" if ratios else "; no domain's rollouts all ran whole")
    cut = (f"; {stopped} with rollouts a monitor stopped (their MSE covers fewer steps than the paper's: not "
           "compared)") if stopped else ""
    ours = f"{len(done)} of 16 domains" + (whole + cut if done else "")
    verdict = (f"GNS beats constant velocity over the same steps on {beats} of {len(done)}" if done
               else "no result yet")
    link = "/".join(tiers)
    papers = [ref.rollout_mse for ref in (domain_reference(s.domain) for s in domain_sweeps()) if ref]
    return [f"| One-step and rollout MSE on 16 domains (Table 1, App. C.4) | {link or '—'} | {ours} | "
            f"{len(papers)} domains, rollout MSE {fmt(min(papers))} to {fmt(max(papers))} | {verdict} | "
            f"{', '.join(_link('domains', t) for t in tiers) or '—'} |"]


def ablation_claims(reports_root: Path) -> list[str]:
    lines = []
    sweeps = {s.name.removeprefix("ablation-"): s for s in (load_sweep(p) for p in discover_sweeps())
              if s.kind == "ablation"}
    for name in sorted(sweeps, key=lambda n: (n not in MAJOR_AXES, MAJOR_AXES.index(n) if n in MAJOR_AXES else n)):
        sweep = sweeps[name]
        (axis,) = sweep.axes
        reference = ablation_reference(axis)
        tier, rows = best_tier(sweep, reports_root)
        kind = "Fig. 4, Sec. 5.4" if name in MAJOR_AXES else "App. C.1"
        if not tier:
            lines.append(f"| {axis} ({kind}) | — | no result yet | {reference.get('summary', '—')} | — | — |")
            continue
        verdicts = judge_axis(axis, rows, reference)
        finished = sum(r.ok for r in rows)
        extra = {q: v for q, v in verdicts.items() if q != ERROR}
        ours = "".join(f"<br>{q}: {v.detail}" for q, v in extra.items())
        verdict = verdicts[ERROR].verdict + "".join(f"<br>{q}: {v.verdict}" for q, v in extra.items())
        paper = reference.get("summary", "—") + (f"<br>{ONE_STEP}: {reference['one_step_summary']}"
                                                 if ONE_STEP in extra else "")
        lines.append(f"| {axis} ({kind}) | {tier} | {finished} of {len(rows)} runs: {verdicts[ERROR].detail}{ours} | "
                     f"{paper} | {verdict} | {_link(sweep.name, tier)} |")
    return lines


def generalisation_claims(reports_root: Path) -> list[str]:
    sweeps = {s.name: s for s in (load_sweep(p) for p in discover_sweeps()) if s.kind == "stress"}
    lines = []
    for name, claim, stable in GENERALISATION:
        sweep = sweeps.get(name)
        tier, rows = best_tier(sweep, reports_root) if sweep else ("", [])
        done = [r for r in rows if r.ok]
        if not done:
            lines.append(f"| {claim} | — | no result yet | see the paper | — | — |")
            continue
        row = done[0]
        scale = row.metric("stress/scale/largest_stable_factor")
        against = relative_to_cv(row)
        interpolation, interpolates = _interpolation(sweep, tier, row, reports_root)
        ours = "; ".join([*interpolation, *_unseen_scenes(row),
                          f"test rollout MSE {fmt(row.metric('rollout_mse'))} ({times(against)} constant velocity)",
                          *_long_rollout(row),
                          *([f"stable at up to {fmt(scale)}x the training scenes' particles"]
                            if math.isfinite(scale) and scale > 0 else [])])
        verdict = "<br>".join(filter(None, [interpolates, _unseen_verdict(row), _horizon_verdict(row, stable),
                                            _scale_verdict(row)]))
        paper = "qualitative (videos)" if stable else "the box loses its shape towards the end (videos)"
        lines.append(f"| {claim} | {tier} | {ours} | {paper} | {verdict or 'see the report'} | "
                     f"{_link('stability', tier)} |")
    return lines


def _interpolation(sweep: SweepSpec, tier: str, row: RunRow, reports_root: Path) -> tuple[list[str], str]:
    """App. C.5's claim, from the per-trajectory rollouts on a grid of contexts (friction angles) that the report
    keeps in its run summary: each rollout's MSE over constant velocity's on the same steps. Each held-out angle
    is paired with the trained angles adjacent to it (the nearest below and above): its error over their
    geometric mean. The model interpolates when the geometric mean of those ratios over the held-out angles has
    its 95% interval below `EQUIVALENCE_MARGIN` (no worse than its neighbours by more than the margin); it does
    not when the interval lies above the margin; else inconclusive. ([], "") where the domain holds nothing out
    or no grid was rolled out."""
    interval = held_out_interval(sweep.domain)
    if interval is None:
        return [], ""
    saved = read_kept(reports_root / sweep.name / tier).get("stress", {}).get(row.run_id, {})
    held, trained = [], []
    for variant in saved.get("generalisation", {}).values():
        for r in variant.get("per_trajectory", []):
            mse, cv = r.get("rollout_mse", math.nan), r.get("baseline_cv_same_steps_mse", math.nan)
            if "context" in r and math.isfinite(mse) and cv > 0:
                (held if interval[0] <= r["context"] <= interval[1] else trained).append((r["context"], mse / cv))
    if not held or not trained:
        return [], ""
    below = [t for t in trained if t[0] < interval[0]]
    above = [t for t in trained if t[0] > interval[1]]
    neighbours = [v for _, v in ([max(below)] if below else []) + ([min(above)] if above else [])]
    reference = float(np.exp(np.mean(np.log(neighbours))))
    paired = mean_interval([math.log(v / reference) for _, v in held])
    ratio_ = Interval(*(math.exp(x) for x in (paired.estimate, paired.low, paired.high)))

    def spread(values: list[float]) -> str:
        median = times(float(np.median(values)))
        return f"median {median}, {fmt(min(values))}-{fmt(max(values))}x ({len(values)} angles)"

    lo, hi = (f"{v:g}" for v in interval)
    ours = [f"rollout MSE over constant velocity's, same steps: held-out angles {lo}-{hi} deg "
            f"{spread([v for _, v in held])}; trained angles {spread([v for _, v in trained])}; held-out against "
            f"the {len(neighbours)} trained angle(s) adjacent to them: {ratio_.text(2, 'x')} (95% interval over "
            f"the held-out angles)"]
    criterion = f"held-out no worse than adjacent trained angles by more than {EQUIVALENCE_MARGIN}x"
    if ratio_.high <= EQUIVALENCE_MARGIN:
        return ours, f"interpolates ({criterion}: the interval's upper end is {fmt(ratio_.high)}x)"
    if ratio_.low > EQUIVALENCE_MARGIN:
        return ours, f"does not interpolate ({criterion}: the interval's lower end is {fmt(ratio_.low)}x)"
    return ours, f"inconclusive ({criterion}: the interval {ratio_.text(2, 'x')} spans the margin)"


def _long_rollout(row: RunRow) -> list[str]:
    """The horizon test (`gns_bench.stress.experiments.horizon`): how far its shortest rollout ran, in steps and in
    training lengths, and the rigid body's drift at its end where the scene has one."""
    steps, ran = row.metric("stress/horizon/steps"), row.metric("stress/horizon/stable_steps")
    if not math.isfinite(steps):
        return []
    length = row.metric("stress/horizon/training_length")
    drift = row.metric("stress/horizon/rigidity_drift_final")
    stopped = row.metric("stress/horizon/stopped") > 0
    parts = [f"long rollout: {ran:,.0f} of {steps:,.0f} steps ({fmt(ran / length)}x the training length of "
             f"{length:,.0f}){f', then {_horizon_stopper(row)} stopped it' if stopped else ''}"]
    if math.isfinite(drift):
        parts.append(f"rigid-body drift {fmt(drift)} at its end (0: rigid; 1: pair distances off by their size)")
    return parts


def _horizon_stopper(row: RunRow) -> str:
    """Which monitor stopped the long rollout first ("a monitor" where its trips tag is gone). The horizon test
    stops on every monitor, out_of_bounds included (a particle through a wall is no stable rollout), where an
    evaluation only flags it and scores on (`eval.stop_on`, reports/NOTES.md)."""
    names = re.findall(r": (\w+) at step (\d+)", row.tag("stress/horizon/trips"))
    return f"the {min(names, key=lambda n: int(n[1]))[0]} monitor" if names else "a monitor"


def _scale_verdict(row: RunRow) -> str:
    """The scale test (Sec. 5.3: stable with up to 34x the training particles): which larger scenes ran their
    whole rollout, and whether the GNS beat constant velocity on the same steps there."""
    factors = sorted(float(k.split("/")[2][1:]) for k in (row.record.metrics if row.record else {})
                     if k.startswith("stress/scale/x") and k.endswith("/steps"))
    parts = []
    for f in factors:
        key = f"stress/scale/x{f:g}/"
        ran, steps = row.metric(key + "stable_steps"), row.metric(key + "steps")
        mse, cv = row.metric(key + "rollout_mse"), row.metric(key + "baseline_cv_same_steps_mse")
        against = f", {times(mse / cv)} constant velocity" if cv > 0 and math.isfinite(mse) else ""
        scene = f"{f:g}x scene ({fmt(row.metric(key + 'particle_ratio'))}x the particles)"
        parts.append(f"{scene} stable{against}" if ran >= steps else
                     f"{scene} stopped at step {ran:,.0f} of {steps:,.0f}{against}")
    return f"larger scenes: {'; '.join(parts)}" if parts else ""


def _horizon_verdict(row: RunRow, stable: bool) -> str:
    """The long rollout against the paper's: where the paper's stays stable (Sec. 5.3), ours must run its whole
    horizon; where the paper reports a slow failure (App. C.7's shaken box deforming towards the end), a monitor
    stopping ours early is a faster failure than the paper's."""
    steps, ran = row.metric("stress/horizon/steps"), row.metric("stress/horizon/stable_steps")
    if not math.isfinite(steps):
        return ""
    factor = ran / row.metric("stress/horizon/training_length")
    if row.metric("stress/horizon/stopped") <= 0:
        return (f"long rollout: stable over the whole {steps:,.0f} steps" +
                (", as the paper's" if stable else ": no failure within the horizon, unlike the paper's"))
    if stable:
        return (f"long rollout: not reproduced ({_horizon_stopper(row)} stopped it at {fmt(factor)}x the training "
                "length)")
    return (f"long rollout: fails sooner than the paper's ({_horizon_stopper(row)} stopped it at step {ran:,.0f} of "
            f"{steps:,.0f})")


def _unseen_scenes(row: RunRow) -> list[str]:
    """What a claim of generalisation is about: per unseen-scene dataset the run rolled out on, its rollout MSE
    beside constant velocity's on the same steps, and how many of its rollouts a monitor stopped."""
    parts = []
    for variant in filter(None, row.tag("generalisation/datasets").split(",")):
        prefix = f"generalisation/{variant}/"
        mse, cv = row.metric(prefix + "rollout_mse"), row.metric(prefix + "baseline_cv_same_steps_mse")
        count = row.metric(prefix + "num_trajectories")
        stopped = row.metric(prefix + "rollout_stopped") * count
        parts.append(f"{variant}: rollout MSE {fmt(mse)} ({times(mse / cv if cv > 0 else math.nan)} constant "
                     f"velocity, same steps; a monitor stopped {fmt(stopped)} of {fmt(count)} rollouts)")
    return parts


def _unseen_verdict(row: RunRow) -> str:
    """Against the trivial baseline on each unseen-scene dataset (the paper's claims there are videos, so
    constant velocity on the same steps is the bar we can compute); empty where the run had none."""
    verdicts = []
    for variant in filter(None, row.tag("generalisation/datasets").split(",")):
        prefix = f"generalisation/{variant}/"
        mse, cv = row.metric(prefix + "rollout_mse"), row.metric(prefix + "baseline_cv_same_steps_mse")
        if math.isfinite(mse) and cv > 0:
            verdicts.append(f"{variant}: GNS {'beats' if mse < cv else 'does not beat'} constant velocity")
    return "<br>".join(verdicts)


def baseline_claims(reports_root: Path) -> list[str]:
    """Sec. 5.5: per baseline sweep, its best run against the GNS's domain run at the same tier, beside the
    paper's ratio (CConv's figures read off the paper's bar chart)."""
    lines = []
    domains = {s.domain: s for s in domain_sweeps()}
    for sweep in (load_sweep(p) for p in discover_sweeps()):
        if sweep.kind != "baseline":
            continue
        tier, rows = best_tier(sweep, reports_root)
        key = sweep.plan("smoke")[0].config.model.architecture
        architecture = simulators.display_name(key)
        ref = domain_reference(sweep.domain)
        paper_baseline = baseline_rollout_mse(ref, key)
        paper = (f"{architecture} / GNS = {fmt(paper_baseline / ref.rollout_mse)}x" if paper_baseline
                 else "GNS learns the cube's rigidity, DPI-Net builds it in")
        claim = f"{display_name(sweep.domain)}: GNS against {architecture} (Sec. 5.5)"
        if not tier:
            lines.append(f"| {claim} | — | no result yet | {paper} | — | — |")
            continue
        gns_rows = collect(domains[sweep.domain], tier, reports_root)
        gns = mean_std([r.metric("rollout_mse") for r in gns_rows])[0]
        best, _ = baselines.chosen_run(sweep, rows)  # as the baselines report chooses it: on validation
        like = baselines.compare(gns_rows, best)
        ours = best.metric("rollout_mse") if best else math.nan
        verdict = {"yes": "GNS better" + (", as in the paper" if paper_baseline else ""),
                   "no": f"{architecture} better" + (": not reproduced" if paper_baseline else ""),
                   "mixed": "mixed (lower error and longer rollouts split)", "—": "—"}[like.verdict]
        # like for like first (the verdict's terms); the raw ratio last, as each covers its own rollout steps
        lines.append(f"| {claim} | {tier} | against constant velocity, same steps: GNS {times(like.gns)}, "
                     f"{architecture} {times(like.baseline)}; rollout steps before a stop: GNS "
                     f"{fmt(like.gns_steps)}, {architecture} {fmt(like.baseline_steps)}; raw rollout MSE, each over "
                     f"its own steps: {architecture} / GNS = {ratio(ours, gns)} ({fmt(ours)} / {fmt(gns)}) "
                     f"| {paper} | {verdict} | {_link(sweep.name, tier)} |")
    return lines


def inference_claim(reports_root: Path) -> list[str]:
    """App. C.6: our rollout time per step against the paper's V100 range for 2D MPM domains."""
    seconds, timed_rows, tier_seen = [], [], set()
    for sweep in domain_sweeps():
        ref = domain_reference(sweep.domain)
        if not ref or ref.dim != 2:
            continue
        tier, rows = best_tier(sweep, reports_root)
        for r in rows:
            if r.ok and math.isfinite(r.metric("rollout_seconds_per_step")):
                seconds.append(r.metric("rollout_seconds_per_step"))
                timed_rows.append(r)
                tier_seen.add(tier)
    paper = inference_reference(2, "MPM (2D)")
    paper_cell = f"{paper['gns_seconds'][0]:g}-{paper['gns_seconds'][1]:g} s/step on a V100" if paper else "—"
    ours = (f"{fmt(min(seconds))}-{fmt(max(seconds))} s/step on {machines(timed_rows)}" if seconds
            else "no result yet")
    tiers = sorted(tier_seen, key=RESULT_TIERS.index)
    return [f"| Rollout time per step, 2D domains (App. C.6) | {'/'.join(tiers) or '—'} | {ours} | {paper_cell} | "
            f"— (other hardware) | {', '.join(_link('domains', t) for t in tiers) or '—'} |"]


def bench_claims(reports_root: Path) -> list[str]:
    """gns-bench's own speed targets, from the committed benchmarks (`gns-bench bench`, one folder per machine):
    one row per target, each machine's measurement in it."""
    from gns_bench.bench.report import machine_benchmarks, machine_name, targets

    by_target: dict[str, list[tuple[str, str, bool, str]]] = {}
    for folder, results in machine_benchmarks(reports_root / "bench"):
        hardware = machine_name(results["environment"])
        for t in targets(results):
            by_target.setdefault(t["target"], []).append((hardware, t["measured"], t["met"], folder))
    if not by_target:
        return ["| Speed targets (`gns-bench bench`) | — | no benchmark yet | — | — | — |"]
    rows = []
    for target, measured in by_target.items():
        ours = "; ".join(f"{hardware}: {value}" for hardware, value, _, _ in measured)
        judged = [ok for _, _, ok, _ in measured if ok is not None]  # None: that machine left the target out
        met = sum(judged)
        verdict = ("not measured" if not judged else "met" if met == len(judged) else "not met" if not met else
                   f"met on {met} of {len(judged)} machines")
        if judged and len(judged) < len(measured):
            verdict += f" ({len(measured) - len(judged)} did not measure it)"
        links = ", ".join(f"[{folder}](bench/{folder}/README.md)" for _, _, _, folder in measured)
        rows.append(f"| {target} (gns-bench's own target) | bench | {ours} | — | {verdict} | {links} |")
    return rows


def _training_key(run) -> str:
    """Planned runs with equal keys train one model (an ablation's default point is its domain's run, a stress
    sweep tests its domain sweep's model): what they train on and with, evaluation and stress settings aside,
    the radius resolved against the domain's default as the runner's keys have it (`resolve_for_domain`: the
    radius ablation's R = 0.015 point is the GOOP run)."""
    config = resolve_for_domain(run.config, run.training_domain).to_dict()
    config.pop("eval", None)
    config.pop("stress", None)
    return json.dumps([run.training_domain, run.dataset_tier, run.dataset_seed, config], sort_keys=True, default=str)


def _to_go(remaining: int, trained: list[RunRow], retrain: int = 0) -> str:
    """The models still to train and the time they would take at the mean training and evaluation time of those
    trained so far: an extrapolation, since later sweeps' domains and models differ (each was budgeted GOOP's
    training time); stress tests' own rollouts are not counted. Where the runs recorded more than
    one CPU generation, also at each generation's own mean: runs took about twice as long on family 25 as on
    family 26 (reports/NOTES.md), so one mean over both hides what the next machine costs. `retrain`: models
    already trained that a stress sweep still to run trains again if their checkpoints are gone (a run summary
    keeps a run's metrics, not its weights: `sweep/runner.py`), stated beside the count, not in it."""
    def estimate(rows: list[RunRow], count: int) -> str:
        per_run = []
        for key in ("train/wall_time_s", "evaluation_seconds"):
            values = [r.metric(key) for r in rows if math.isfinite(r.metric(key))]
            per_run.append(sum(values) / len(values) if values else 0.0)
        return format_duration(count * sum(per_run))

    text = "none"
    if remaining > 0:
        text = f"{remaining} model{'s' if remaining > 1 else ''}, about {estimate(trained, remaining)}"
        by_generation: dict[str, list[RunRow]] = {}
        for row in trained:
            if generation := run_cpu_generation(row):
                by_generation.setdefault(generation, []).append(row)
        if len(by_generation) > 1:
            text += " (at the mean of " + "; ".join(
                f"CPU {generation}'s {len(rows)} run{'s' * (len(rows) > 1)}: {estimate(rows, remaining)}"
                for generation, rows in sorted(by_generation.items())) + ")"
    if retrain > 0:
        text += (f"; and {retrain} trained model{'s' * (retrain > 1)} again (about {estimate(trained, retrain)}) "
                 f"if {'their checkpoints are' if retrain > 1 else 'its checkpoint is'} gone when the stress "
                 f"sweeps test {'them' if retrain > 1 else 'it'}")
    return text


def campaign_section(reports_root: Path, campaign_file: Path = CAMPAIGNS_DIR / "paper.toml",
                     sweeps_dir: Path = SWEEPS_DIR, tiers: tuple[str, ...] = CAMPAIGN_TIERS) -> list[str]:
    """What the campaign has trained at each tier and what that cost: models trained against those
    planned (each trained once however many sweeps share it), training and evaluation time summed over them,
    what is left at the mean so far (`_to_go`), and the machines that ran them."""
    campaign = load_campaign(campaign_file, sweeps_dir)
    sweeps = [load_sweep(path, sweeps_dir) for path in campaign.sweeps]
    lines = []
    for tier in tiers:
        planned = {_training_key(run) for sweep in sweeps for run in sweep.plan(tier)}
        rows = [r for sweep in sweeps for r in collect(sweep, tier, reports_root)]
        trained = {r.run_id: r for r in rows if r.ok and not r.tag("shared_from")}.values()  # copies left out
        if not trained:
            continue
        by_model: dict = {}
        for r in sorted(trained, key=lambda r: r.record.start_time):  # the first training of each model counts
            by_model.setdefault(_training_key(r.planned), []).append(r)

        def hours(runs) -> float:
            return sum(r.metric("train/wall_time_s") for r in runs if math.isfinite(r.metric("train/wall_time_s")))

        training = format_duration(hours(runs[0] for runs in by_model.values()))
        repeats = [r for runs in by_model.values() for r in runs[1:]]  # a model trained again (a stress sweep's)
        if repeats:
            training += f" (+{format_duration(hours(repeats))} on {len(repeats)} repeat training(s))"
        timed = [r.metric("evaluation_seconds") for r in trained if math.isfinite(r.metric("evaluation_seconds"))]
        evaluation = (format_duration(sum(timed)) + (f" ({len(timed)} of {len(trained)} runs logged it)"
                                                     if len(timed) < len(trained) else "")) if timed else "—"
        ran_on = machines(trained)
        models = {_training_key(r.planned) for r in trained}  # a model a stress sweep trained again counts once
        stress_waiting = {_training_key(r.planned) for r in rows if r.planned.config.stress.enabled and not r.ok}
        to_go = _to_go(len(planned - models), list(trained), retrain=len(stress_waiting & models))
        lines.append(f"| {tier} | {len(models)} of {len(planned)} | {training} | {evaluation} | "
                     f"{to_go} | {ran_on} |")
    if not lines:
        return []
    return [f"## The campaign (`sweeps/campaigns/{campaign_file.name}`)", "",
            f"{campaign.description}. Models trained against those it plans (a model several sweeps share counts "
            "once), and the time they took: training as each model's first run's `train/wall_time_s` (stalls clipped, "
            "periodic evaluation left out; a model trained again is counted apart), evaluation as its "
            "`evaluation_seconds` (every test rollout and metric). What is "
            "left is extrapolated at the mean training and evaluation time of the models trained so far, and at each "
            "CPU generation's mean where the runs came from more than one (their step rates differ); the stress "
            "tests' own rollouts are not counted. A stress sweep tests the checkpoint of its domain's model; where "
            "that checkpoint was lost with the store that held it (reports/NOTES.md), it trains the model again, "
            "and the time that would take is stated after the count.", "",
            "| tier | models trained | training time | evaluation time | to go, at the mean so far | machines |",
            "|---|---|---|---|---|---|",
            *lines, ""]


def write_index(reports_root: Path = Path("reports"), out: Path | None = None) -> Path:
    """`reports_root/README.md` (or `out`): where gns-bench stands on each claim of the paper."""
    lines = ["# gns-bench against the paper", "",
             "Where this suite stands on each claim of *Learning to Simulate Complex Physics with Graph Networks* "
             "(Sanchez-Gonzalez et al., ICML 2020). Each row is shown at the most thorough tier with a finished run "
             "(`paper`: the paper's budget; `cpu`: the protocol for 2-core CPUs, chosen by "
             "[study-cpu_budget](study-cpu_budget/); `small`: the earlier CPU protocol); smoke runs only check "
             "the pipeline. Verdicts are computed from the numbers (`gns_bench/report/verdict.py`); every row "
             "links to the report with its budget, its metrics' definitions and its runs. Generated by "
             "`gns-bench report index` from the run summaries committed beside each report; "
             "[NOTES.md](NOTES.md) keeps what earlier sessions learned.", "",
             *campaign_section(reports_root),
             "## Accuracy across domains", "", HEADER, "|---|---|---|---|---|---|", *domain_claim(reports_root), "",
             "## Ablations (major axes first)", "",
             "An ablation's error is compared over the same steps for every run: the whole-rollout MSE when no "
             "rollout was stopped, else the MSE over the first steps every rollout reached; where a health monitor "
             "stopped rollouts, a second verdict compares how many steps they ran before the stop; where Sec. 5.4 "
             "states a direction for the one-step error as well, a third judges the one-step MSE. Each comparison "
             "is a ratio of geometric means over seeds with its 95% interval: a direction (Sec. 5.4) is reproduced "
             "when the interval lies wholly on the paper's side of 1, App. C.1's findings of little difference only "
             "by an equivalence test (90% interval within 1.25x, two seeds a side or more); runs on different CPU "
             "kinds are not compared.", "", HEADER, "|---|---|---|---|---|---|",
             *ablation_claims(reports_root), "",
             "## Generalisation and stability", "", HEADER, "|---|---|---|---|---|---|",
             *generalisation_claims(reports_root), "",
             "## Baselines (Sec. 5.5, App. D)", "", HEADER, "|---|---|---|---|---|---|",
             *baseline_claims(reports_root), "",
             "## Speed", "", HEADER, "|---|---|---|---|---|---|", *inference_claim(reports_root),
             *bench_claims(reports_root), ""]
    path = out or reports_root / "README.md"
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path
