"""The baselines report, `reports/baselines/<tier>/README.md`: the paper's comparison of GNS with CConv and
DPI-Net (Sec. 5.5, App. D.1) reproduced. Per comparison domain, the GNS (the domain sweep's run at the tier)
beside the baseline's best run (`sweeps/baselines/`), ours and the paper's, with the ratio baseline / GNS for
each (ours over the same rollout steps for both models); where the domain holds a rigid body (BOXBATH's cube)
every model's rigidity drift against the ground truth; where the paper shows a baseline failing (BOXBATH, GOOP)
one test trajectory drawn by every model side by side (the cube losing its shape, the goop blowing apart)."""

from __future__ import annotations

import dataclasses
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gns_bench import simulators  # noqa: E402
from gns_bench.config import StressConfig  # noqa: E402
from gns_bench.data.format import RIGID_PARTICLE_TYPE  # noqa: E402
from gns_bench.evaluate.plots import STEP_LABEL, config_colours  # noqa: E402
from gns_bench.evaluate.result import RolloutResult  # noqa: E402
from gns_bench.report import figures  # noqa: E402
from gns_bench.report.cells import (  # noqa: E402
    budget_statement,
    definitions_section,
    fmt,
    machines,
    ratio,
    relative_to_cv,
    run_ids_cell,
    shared_cores_mark,
    times,
)
from gns_bench.report.collect import (  # noqa: E402
    RunRow,
    collect,
    domain_sweeps,
    load_rollouts,
    mean_std,
    stress_sweeps,
)
from gns_bench.report.kept import read_kept, write_kept  # noqa: E402
from gns_bench.report.reference import (  # noqa: E402
    baseline_failures,
    baseline_rollout_mse,
    display_name,
    domain_reference,
)
from gns_bench.report.verdict import error_measure  # noqa: E402
from gns_bench.sweep.spec import PlannedRun, SweepSpec, discover_sweeps, load_sweep  # noqa: E402

HEADER = ("| domain | GNS (ours) | baseline (ours, best run) | baseline / GNS (ours, same steps) | "
          "against constant velocity, same steps: GNS / baseline | rollout steps covered: GNS / baseline | "
          "GNS better here? | GNS (paper) | CConv (paper) | CConv / GNS (paper) | MLflow runs |")
VERDICT_RULE = ("Computed from the table: *yes* when the GNS's rollout MSE against constant velocity's over the "
                "same steps is lower and its rollouts ran at least as far before any monitor stopped them, *no* when "
                "the baseline wins on both, *mixed* otherwise. One run a point at this tier, so a small difference "
                "is within what a second seed could change.")
DPI = 80


def baseline_sweeps() -> list[SweepSpec]:
    return [s for s in (load_sweep(p) for p in discover_sweeps()) if s.kind == "baseline"]


def same_model(a: PlannedRun, b: PlannedRun) -> bool:
    """Whether two planned runs train the same model on the same data: equal configs but for [stress] (a stress
    sweep retrains a domain sweep's model when that run's checkpoint is gone, `sweep/runner.py`)."""
    unstressed = [dataclasses.replace(r.config, stress=StressConfig()) for r in (a, b)]
    return (unstressed[0] == unstressed[1] and (a.training_domain, a.dataset_tier, a.dataset_seed, a.eval_dataset_tier)
            == (b.training_domain, b.dataset_tier, b.dataset_seed, b.eval_dataset_tier))


def gns_rollouts(gns: RunRow | None, stand_ins: list[RunRow], workdir: Path) -> tuple[list[RolloutResult], str]:
    """The GNS's rollouts for the pictures, and where they came from: the domain sweep's run, or, when its
    artifacts are gone (a run known only from its committed summary), a finished stress-sweep run that trained the
    same model again (`same_model`), named in the report beside its own rollout MSE ('' when the domain run's own,
    or none)."""
    rollouts = _rollouts(gns, workdir / "gns")
    if rollouts or gns is None:
        return rollouts, ""
    for row in stand_ins:
        if row.ok and row.tag("stress_tested") != "here" and same_model(row.planned, gns.planned):
            rollouts = _rollouts(row, workdir / row.planned.sweep)
            if rollouts:
                return rollouts, (f"the domain run's rollouts are gone with the MLflow store that made it, so these "
                                  f"are of {row.planned.sweep}/{row.planned.name} (`{row.run_id}`), which trained "
                                  f"the same config again: rollout MSE {fmt(row.metric('rollout_mse'))} against the "
                                  f"domain run's {fmt(gns.metric('rollout_mse'))}")
    return [], ""


def architecture_of(sweep: SweepSpec) -> str:
    return sweep.plan("smoke")[0].config.model.architecture


def best_run(rows: list[RunRow]) -> RunRow | None:
    """The baseline's best run, as the paper took CConv's best after its sweep (Sec. 5.5): the lowest rollout MSE
    against constant velocity's over the same steps (like for like when monitors stopped rollouts early, where
    the raw rollout MSE covers few steps and reads low)."""
    done = [r for r in rows if r.ok and math.isfinite(relative_to_cv(r))]
    return min(done, key=relative_to_cv, default=None)


def validation_error(row: RunRow) -> float:
    """A run's error on the validation split: its training curve's last point (`train.eval_every`, on the first
    validation trajectories), rollout MSE over constant velocity's on the same steps; NaN where none was logged."""
    baseline = row.metric("curve/baseline_cv_same_steps_mse")
    return row.metric("curve/rollout_mse") / baseline if baseline > 0 else math.nan


def chosen_run(sweep: SweepSpec, rows: list[RunRow]) -> tuple[RunRow | None, str]:
    """The baseline's setting to set beside the GNS, and how it was chosen. As the paper tuned CConv by a sweep
    (Sec. 5.5, App. D.1), the run with the lowest validation error (`validation_error`) when every finished run
    has one; the test split only scores the choice. Without a validation measurement there is nothing fair to
    choose by (the test split would score its own choice): the run at the sweep's default setting stands in."""
    done = [r for r in rows if r.ok]
    if done and all(math.isfinite(validation_error(r)) for r in done):
        return min(done, key=validation_error), "chosen on the validation split"
    default = [r for r in done if all(_matches(r.planned.axes.get(k), v) for k, v in sweep.default.items())]
    if default and sweep.default:
        return default[0], "the default setting (no validation error logged to choose by)"
    return (done[0], "its only setting") if len(done) == 1 else (None, "")


def _matches(a: object, b: object) -> bool:
    if isinstance(a, float | int) and isinstance(b, float | int) and not isinstance(a, bool):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-15)
    return a == b


@dataclass(frozen=True)
class Comparison:
    """The GNS (mean over its domain sweep's runs) against a baseline's best run, like for like."""

    gns: float  # rollout MSE / constant velocity's over the same steps
    baseline: float
    gns_steps: float  # rollout steps covered, mean over the test rollouts (a monitor's stop ends one early)
    baseline_steps: float

    @property
    def verdict(self) -> str:
        """"yes" when the GNS has the lower error against constant velocity and its rollouts ran at least as
        far, "no" when the baseline wins on both, "mixed" otherwise, "—" when either is unknown."""
        if not all(math.isfinite(v) for v in (self.gns, self.baseline, self.gns_steps, self.baseline_steps)):
            return "—"
        if self.gns < self.baseline and self.gns_steps >= self.baseline_steps:
            return "yes"
        if self.gns > self.baseline and self.gns_steps <= self.baseline_steps:
            return "no"
        return "mixed"

    def sentence(self) -> str:
        reasons = {"yes": "lower error and rollouts that ran as far", "no": "the baseline's error is lower and its "
                   "rollouts ran as far", "mixed": "the lower error and the longer rollouts are not the same model's"}
        return (f"{reasons[self.verdict]}: {fmt(self.gns)}x against {fmt(self.baseline)}x constant velocity's "
                f"error over the same steps; rollouts covered {self.gns_steps:.0f} against "
                f"{self.baseline_steps:.0f} steps")


def compare(gns_rows: list[RunRow], best: RunRow | None) -> Comparison:
    done = [r for r in gns_rows if r.ok]
    nan = math.nan
    return Comparison(mean_std([relative_to_cv(r) for r in done])[0] if done else nan,
                      relative_to_cv(best) if best else nan,
                      mean_std([r.metric("rollout_steps") for r in done])[0] if done else nan,
                      best.metric("rollout_steps") if best else nan)


def comparison_row(sweep: SweepSpec, rows: list[RunRow], gns_rows: list[RunRow], compare_runs: bool) -> list[str]:
    ref = domain_reference(sweep.domain)
    gns = mean_std([r.metric("rollout_mse") for r in gns_rows])[0]
    best, how = chosen_run(sweep, rows)
    ours = best.metric("rollout_mse") if best else math.nan
    architecture = architecture_of(sweep)
    paper_cconv = baseline_rollout_mse(ref, architecture)
    like = compare(gns_rows, best)
    return [f"{display_name(sweep.domain)} ({architecture})", fmt(gns),
            fmt(ours) + (f" (`{best.planned.name}`: {how})" if best else ""),
            same_steps_ratio(gns_rows, best) if compare_runs and best else "—",
            f"{times(like.gns)} / {times(like.baseline)}" if compare_runs else "—",
            f"{fmt(like.gns_steps)} / {fmt(like.baseline_steps)}" if compare_runs else "—",
            like.verdict if compare_runs else "—",
            fmt(ref.rollout_mse) if ref else "—", fmt(paper_cconv) if paper_cconv else "—",
            ratio(paper_cconv, ref.rollout_mse) if paper_cconv and ref else "—",
            run_ids_cell([r for r in [*gns_rows, *rows] if r.run_id])]


def same_steps_ratio(gns_rows: list[RunRow], best: RunRow) -> str:
    """The baseline's error over the GNS's mean, over the same rollout steps for every run (`verdict.error_measure`:
    the whole rollout when none stopped, else the largest horizon all reached), with the steps named."""
    key, words = error_measure([*gns_rows, best])
    gns = mean_std([r.metric(key) for r in gns_rows if r.ok])[0] if key else math.nan
    if not key or not gns > 0:
        return "— (no horizon every rollout reached)"
    ours = best.metric(key)
    return f"{ratio(ours, gns)} ({fmt(ours)} / {fmt(gns)}, {words})"


@dataclass(frozen=True)
class Cost:
    """One model's cost on one domain beside its error (the comparison's time against error, Sec. 5.5)."""

    domain: str
    model: str  # "GNS", "CConv", "DPI-Net"
    train_seconds_per_step: float  # training wall time over its steps (mean over the model's runs)
    train_seconds: float
    rollout_seconds_per_step: float
    against_cv: float  # rollout MSE / constant velocity's, same steps
    hardware: str


def _cost(domain: str, model: str, rows: list[RunRow]) -> Cost | None:
    done = [r for r in rows if r.ok]
    if not done:
        return None

    def mean(values: list[float]) -> float:
        return mean_std(values)[0]
    return Cost(domain, model, mean([r.metric("train/wall_time_s") / r.metric("train/final_step") for r in done]),
                mean([r.metric("train/wall_time_s") for r in done]),
                mean([r.metric("rollout_seconds_per_step") for r in done]),
                mean([relative_to_cv(r) for r in done]),
                machines(done)
                + shared_cores_mark(done))


def costs(collected: list[tuple[SweepSpec, list[RunRow], list[RunRow]]]) -> list[Cost]:
    """Per comparison domain, the GNS's cost (its domain runs, once a domain) and each baseline's best run's."""
    out, seen = [], set()
    for sweep, rows, gns_rows in collected:
        name = display_name(sweep.domain)
        best, _ = chosen_run(sweep, rows)
        for model, model_rows in (("GNS", gns_rows), (simulators.display_name(architecture_of(sweep)),
                                                      [best] if best else [])):
            cost = _cost(name, model, model_rows) if (name, model) not in seen else None
            if cost is not None:
                seen.add((name, model))
                out.append(cost)
    return out


MEASURED = "measured_cost"  # the summary extra that keeps `bench.costs.measure_costs`' result between regenerations


def measured_section(measured: dict[str, Any] | None) -> list[str]:
    """The table of `bench.costs.measure_costs`: per domain each model's training and rollout time a step,
    measured on one machine in one sitting, and the baseline's over the GNS's."""
    if not measured or not measured.get("rows"):
        return []
    models = list(simulators.display_names().values())  # the GNS first
    rows = sorted(measured["rows"], key=lambda r: (r["domain"], models.index(r["model"])))
    dirty = " (with uncommitted changes)" if measured["git_sha"].endswith("-dirty") else ""
    lines = ["### Measured side by side", "",
             f"Measured on **{measured['hardware']}** (CPU {measured['cpu']}) on {measured['date']}, at commit "
             f"`{measured['git_sha'][:10]}`{dirty}, one model after another: {measured['steps']} steps of each "
             f"run's own training loop on its {measured['tier']}-tier data (the precision and compile settings it "
             "chooses there), and its evaluation's rollout steps on the test split (neighbour search included). "
             "Unlike the table above, every number here comes from the same machine and the same code (`gns-bench "
             "report baselines --measure-cost`).", "",
             "| domain | model | training s/step | rollout s/step | training / GNS's | rollout / GNS's | settings |",
             "|---|---|---|---|---|---|---|"]
    gns = {r["domain"]: r for r in rows if r["model"] == "GNS"}
    for r in rows:
        base = gns.get(r["domain"])
        over = ((ratio(r["train_seconds_per_step"], base["train_seconds_per_step"]),
                 ratio(r["rollout_seconds_per_step"], base["rollout_seconds_per_step"]))
                if base and r["model"] != "GNS" else ("—", "—"))
        lines.append(f"| {r['domain']} | {r['model']} | {fmt(r['train_seconds_per_step'])} | "
                     f"{fmt(r['rollout_seconds_per_step'])} | {over[0]} | {over[1]} | {r['settings']} |")
    if measured.get("missing"):
        lines += ["", "Not measured: " + "; ".join(measured["missing"]) + "."]
    return lines + [""]


# One colour per model in every figure of this report, distinct by construction (`config_colours` of the
# display names; the architectures' keys would hash GNS and DPI-Net onto one colour).
MODEL_COLOURS = config_colours(simulators.display_names().values())


def cost_figure(points: list[Cost], path: Path) -> Path | None:
    """Error against constant velocity's (same steps) over training and rollout time a step, one point per model
    and domain, coloured by model."""
    points = [c for c in points if all(math.isfinite(v) and v > 0 for v in
                                       (c.train_seconds_per_step, c.rollout_seconds_per_step, c.against_cv))]
    if not points:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.4))
    models = list(dict.fromkeys(c.model for c in points))
    for ax, attribute, label in ((axes[0], "train_seconds_per_step", "training time a step (s)"),
                                 (axes[1], "rollout_seconds_per_step", "rollout time a step (s)")):
        for model in models:
            mine = [c for c in points if c.model == model]
            ax.scatter([getattr(c, attribute) for c in mine], [c.against_cv for c in mine], s=24,
                       color=MODEL_COLOURS.get(model, "0.4"), label=model, zorder=3)
            for c in mine:
                ax.annotate(c.domain, (getattr(c, attribute), c.against_cv), fontsize=6, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.axhline(1.0, color="0.6", lw=0.8, ls="--")  # constant velocity's own error
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel("rollout MSE / constant velocity's,\nsame steps", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.margins(0.2)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def cost_section(collected: list[tuple[SweepSpec, list[RunRow], list[RunRow]]], out_dir: Path,
                 measured: dict[str, Any] | None = None) -> list[str]:
    rows = costs(collected)
    if not rows:
        return []
    lines = ["## Cost beside error", "", "Each model's training time a step (its training wall time over its steps, "
             "batch as its config sets it) and rollout time a step, on the machine its runs name, beside its rollout "
             "MSE against constant velocity's over the same steps (below 1x beats the trivial baseline). Runs "
             "trained on different machines, or before a model's code was made faster, do not compare here; the "
             "times measured side by side below do.", "",
             "| domain | model | training s/step | training time (s) | rollout s/step | against constant velocity, "
             "same steps | hardware |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {c.domain} | {c.model} | {fmt(c.train_seconds_per_step)} | {fmt(c.train_seconds)} | "
              f"{fmt(c.rollout_seconds_per_step)} | {times(c.against_cv)} | {c.hardware} |" for c in rows]
    same_machine = {(r["domain"], r["model"]): r for r in (measured or {}).get("rows", [])}
    if same_machine:  # the figure at the times measured side by side: like for like
        rows = [dataclasses.replace(c, **{k: same_machine[c.domain, c.model][k] for k in
                                          ("train_seconds_per_step", "rollout_seconds_per_step")})
                for c in rows if (c.domain, c.model) in same_machine]
    figure = cost_figure(rows, out_dir / "cost_vs_error.png")
    if figure is not None:
        lines += ["", f"![cost against error]({figure.name})", "",
                  "Times in the figure: " + ("measured side by side on one machine (below); the error, each run's."
                                             if same_machine else "each run's own, on the machine it names.")]
    return lines + ["", *measured_section(measured)]


def verdict_lines(collected: list[tuple[SweepSpec, list[RunRow], list[RunRow]]]) -> list[str]:
    """One line per comparison: does the GNS beat the baseline here, and did it in the paper."""
    lines = ["## Verdicts", "", f"Does the GNS beat the baseline here? {VERDICT_RULE}", ""]
    return lines + [verdict_line(sweep, rows, gns_rows) for sweep, rows, gns_rows in collected] + [""]


def verdict_line(sweep: SweepSpec, rows: list[RunRow], gns_rows: list[RunRow]) -> str:
    """Does the GNS beat this baseline sweep's best run here (`Comparison.verdict`), and did it in the paper."""
    ref = domain_reference(sweep.domain)
    name, architecture = display_name(sweep.domain), architecture_of(sweep)
    like = compare(gns_rows, chosen_run(sweep, rows)[0])
    baseline = simulators.display_name(architecture)
    if like.verdict == "—":
        return f"- {name}, GNS against {baseline}: not both run yet."
    paper = ""
    paper_baseline = baseline_rollout_mse(ref, architecture)
    if paper_baseline and ref.rollout_mse:
        paper = (f" The paper: GNS better ({fmt(ref.rollout_mse)} against about {fmt(paper_baseline)} "
                 f"rollout MSE, {ratio(paper_baseline, ref.rollout_mse)}).")
    return f"- {name}, GNS against {baseline}: **{like.verdict}**, {like.sentence()}.{paper}"


def _rollouts(row: RunRow | None, workdir: Path) -> list[RolloutResult]:
    if row is None:
        return []
    return load_rollouts(row.artifact_run_id, f"evaluation/{row.split}_rollouts.npz", workdir)


def rigidity_means(rollouts: list[RolloutResult]) -> dict[str, list[float]] | None:
    """BOXBATH: the cube's drift of one model, mean over its test rollouts, and the ground truth's over the same
    steps (to the shortest rollout: a monitor's stop ends one early); None without a rigid body. Plain lists:
    the report's summary keeps them, so the figure is redrawn when the rollouts are gone."""
    curves = [c for r in rollouts if (c := figures.rigidity_curves(r, RIGID_PARTICLE_TYPE)) is not None]
    if not curves:
        return None
    length = min(len(c[0]) for c in curves)

    def compact(values: np.ndarray) -> list[float]:  # 4 significant digits: the figure's resolution, a small file
        return [float(f"{v:.4g}") for v in values]

    return {"model": compact(np.nanmean([c[0][:length] for c in curves], axis=0)),
            "truth": compact(np.nanmean([c[1][:length] for c in curves], axis=0))}


def rigidity_comparison(means: dict[str, dict[str, list[float]]], path: Path) -> list[str]:
    """BOXBATH: the cube's drift (`rigidity_means`) for each model (keyed by display name) and the ground truth,
    one figure. Returns the names of the models drawn (none: no figure written)."""
    drawn = [name for name, curve in means.items() if curve]
    if not drawn:
        return []
    fig, ax = plt.subplots(figsize=(5.6, 3.6), layout="constrained")
    for name in drawn:
        model = np.asarray(means[name]["model"], float)
        # wide, under the truth's thin dashes: a model that keeps the cube rigid (DPI-Net, by construction) lies
        # on the ground truth's line and must still show
        ax.plot(np.arange(model.size), model, color=MODEL_COLOURS.get(name, "0.4"), lw=2.4, zorder=2,
                label=f"{name} (at step {model.size - 1}: {model[-1]:.3g})")
    truth = max((np.asarray(means[n]["truth"], float) for n in drawn), key=len)
    ax.plot(np.arange(truth.size), truth, color="k", ls="--", lw=1.0, zorder=3, label="ground truth")
    ax.set_xlabel(STEP_LABEL)
    ax.set_ylabel("rigidity drift (relative)")
    ax.set_title("BOXBATH: the cube's shape over a rollout (0: rigid)", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return drawn


def kept_rigidity(previous: dict, name: str, row: RunRow | None) -> dict[str, list[float]] | None:
    """The drift curve the last report kept for model `name`, if it was drawn from the run that is still this
    model's best (`row`): a rerun's or another run's curve would be the wrong one."""
    kept = previous.get("rigidity_curves", {}).get(name)
    return kept if kept and row is not None and kept.get("run_id") == row.run_id else None


MISSING_ROLLOUTS = ("its run's rollouts are not in this MLflow store: a run known only from its committed summary "
                    "keeps its numbers, not its artifacts")


def failure_section(collected: list[tuple[SweepSpec, list[RunRow], list[RunRow]]], out_dir: Path,
                    previous: dict | None, stand_ins: dict[str, list[RunRow]] | None = None) -> tuple[list[str], dict]:
    """For each domain where the paper shows a baseline failing (`reference.baseline_failures`) with runs:
    test trajectory 0 as the GNS and each baseline's best run rolled it out (`<domain>_strip.png`: every model
    whose rollouts are here, the missing ones named), and where it holds a rigid body (BOXBATH's cube) every
    model's rigidity drift. Returns the lines and what was drawn, which the summary keeps: when MLflow no longer
    holds the rollouts, the pictures the last report drew stand (`previous`, that summary's record).
    `stand_ins`: per domain, the stress sweeps' runs whose rollouts stand in for the GNS's when its own are gone
    (`gns_rollouts`)."""
    lines, drawn = [], {}
    for failure in baseline_failures():
        domain = failure.domain
        here = [(s, rows, gns) for s, rows, gns in collected if s.domain == domain]
        if not here:
            continue
        best = {"gns": best_run(here[0][2]),
                **{architecture_of(sweep): chosen_run(sweep, rows)[0] for sweep, rows, _ in here}}
        with tempfile.TemporaryDirectory() as tmp:
            gns, gns_from = gns_rollouts(best["gns"], (stand_ins or {}).get(domain, []), Path(tmp))
            models = {"gns": gns, **{name: _rollouts(row, Path(tmp) / name) for name, row in best.items()
                                     if name != "gns"}}
        record = before = (previous or {}).get(domain, {})
        if any(models.values()):  # drawn afresh; else the last report's pictures stand
            record = {"gns_from": gns_from} if gns_from else {}
            # a model without rollouts here is left out of the pictures, and the report says why
            missing = {simulators.display_name(name): "not run yet" if best[name] is None else MISSING_ROLLOUTS
                       for name, rollouts in models.items() if not rollouts}
            if missing:
                record["missing"] = missing
            if failure.rigidity:
                # each model's curve from its rollouts here, else the one the last report kept of the same run
                curves = {}
                for key, rollouts in models.items():
                    name, row = simulators.display_name(key), best[key]
                    means = rigidity_means(rollouts)
                    if means and row is not None:
                        curves[name] = {**means, "run_id": row.run_id,
                                        **({"drawn_from": gns_from} if key == "gns" and gns_from else {})}
                    elif (kept := kept_rigidity(before, name, row)) is not None:
                        curves[name] = kept
                record["rigidity"] = rigidity_comparison(curves, out_dir / f"{domain}_rigidity.png")
                if curves:
                    record["rigidity_curves"] = curves
                kept_names = [name for name in record["rigidity"] if name in missing]
                if kept_names:
                    record["rigidity_kept"] = kept_names
            shown = [(simulators.display_name(name), rollouts[0]) for name, rollouts in models.items()
                     if rollouts and rollouts[0].predicted.shape[0]]
            if shown:  # the baselines alone where the GNS's rollouts are gone: the failure is theirs to show
                record["strip"] = [name for name, _ in shown]
                figures.rollout_strip(shown, out_dir / f"{domain}_strip.png", f"{display_name(domain)}: test "
                                      f"trajectory 0 as {', '.join(record['strip'])} rolled it out")
        if not record:
            continue
        drawn[domain] = record
        name = display_name(domain)
        lines += [f"## {name}: the failure the paper shows", "",
                  f"In the paper (Sec. 5.5) {failure.words}.", ""]
        if record.get("gns_from"):
            lines += [f"The GNS in these pictures: {record['gns_from']}.", ""]
        if record.get("missing"):
            lines += ["Not drawn: " + "; ".join(f"{name} ({why})" for name, why in record["missing"].items()) + ".",
                      ""]
        if record.get("strip") and (out_dir / f"{domain}_strip.png").is_file():
            models_drawn = ", ".join(record["strip"])
            lines += [f"Test trajectory 0, the ground truth above each model's rollout ({models_drawn}; each "
                      "baseline's best run), at the same steps; a panel after a model's rollout was stopped by a "
                      "health monitor says so.", "", f"![{name}: every model's rollout]({domain}_strip.png)", ""]
        if record.get("rigidity") and (out_dir / f"{domain}_rigidity.png").is_file():
            lines += ["The cube's rigidity drift, mean over the test rollouts (RMS change of its pairwise distances "
                      "since the rollout began, relative to their RMS): the GNS has to learn rigidity, DPI-Net has it "
                      "built in (a rigid projection and root nodes), CConv neither."
                      + (f" Drawn: {', '.join(record['rigidity'])}." if isinstance(record["rigidity"], list) else "")
                      + (f" The curve of {', '.join(record['rigidity_kept'])} is the one the last report drew from "
                         "the same run and kept in its summary (`runs.json`): the rollouts themselves are gone."
                         if record.get("rigidity_kept") else "")
                      + "".join(f" {name}'s curve: {curve['drawn_from']}." for name, curve in
                                record.get("rigidity_curves", {}).items()
                                if curve.get("drawn_from") and name in record.get("rigidity_kept", [])),
                      "",
                      f"![rigidity]({domain}_rigidity.png)", ""]
    return lines, drawn


def write_baselines_report(tier: str, out_dir: Path, reports_root: Path | None = None,
                           measured: dict[str, Any] | None = None) -> Path:
    """`measured`: a fresh `bench.costs.measure_costs` result; by default the one the summary already keeps."""
    out_dir.mkdir(parents=True, exist_ok=True)
    extras = read_kept(out_dir)
    measured = measured or extras.get(MEASURED)
    reports_root = reports_root or out_dir.parent.parent
    domains = {s.domain: s for s in domain_sweeps()}
    compare = tier != "smoke"
    collected = [(s, collect(s, tier, reports_root), collect(domains[s.domain], tier, reports_root))
                 for s in baseline_sweeps()]
    every = [r for _, rows, gns in collected for r in [*rows, *gns]]
    lines = [f"# Baselines ({tier} tier)", "", budget_statement(every, tier), "",
             "The paper compares the GNS with continuous convolutions (CConv, Ummenhofer et al. 2020) on six domains "
             "and with DPI-Net (Li et al. 2019) on BOXBATH (Sec. 5.5, App. D.1). Here each baseline's best run "
             "(`sweeps/baselines/`) stands beside the GNS run of its domain sweep at the same tier; the paper's "
             "CConv figures are read off its bar chart (approximate).", "", *definitions_section(),
             "## Rollout MSE against the paper's", "", HEADER, "|" + "---|" * HEADER.count(" | ") + "---|",
             *("| " + " | ".join(comparison_row(s, rows, gns, compare)) + " |" for s, rows, gns in collected), "",
             *(verdict_lines(collected) if compare else []), *cost_section(collected, out_dir, measured)]
    stand_ins = {d: [r for s in stress_sweeps() if s.domain == d for r in collect(s, tier, reports_root)]
                 for d in (failure.domain for failure in baseline_failures())}
    failures, drawn = failure_section(collected, out_dir, extras.get("failures"), stand_ins)
    lines += failures
    kept = {**({"failures": drawn} if drawn else {}), **({MEASURED: measured} if measured else {})}
    write_kept(out_dir, "baselines", tier, kept,
               note="written by gns-bench report baselines: the pictures it drew, which it keeps when MLflow no "
                    "longer holds the runs (their numbers are in each baseline sweep's own summary), and the costs "
                    "measured side by side (--measure-cost)")
    path = out_dir / "README.md"
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path
