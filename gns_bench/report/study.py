"""Reports of studies that compare named candidates (`[candidates]` sweeps, e.g. sweeps/studies/cpu_budget.toml):
a table of every candidate on the same test trajectories, and error against training time from the curves the
runs logged along the way (`train.eval_every`: `curve/<metric>` at each evaluated step, with
`curve/train_seconds`). The winner is the candidate with the lowest rollout MSE at the end of its budget, mean
over seeds, named only when its seeds' spread keeps it clear of the runner-up."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import NullFormatter  # noqa: E402

from gns_bench.report.cells import (  # noqa: E402
    DIAGNOSTIC_COLUMNS,
    MISSING,
    fmt,
    machines,
    mean_cell,
    relative_to_cv,
    run_ids_cell,
    shared_cores_mark,
    steps_covered,
)
from gns_bench.report.collect import RunRow, collect, mean_std  # noqa: E402
from gns_bench.report.reference import domain_reference  # noqa: E402
from gns_bench.report.trend import PowerLaw, fit_power_law, holds_from, settled_step  # noqa: E402
from gns_bench.sweep.spec import CANDIDATE_AXIS, SweepSpec, discover_sweeps, load_sweep  # noqa: E402

# What the error-against-time figure draws: the rollout MSE over constant velocity's on the same steps (like for
# like however early a monitor stopped a rollout; an untrained model's rollouts stop at once, so its raw rollout
# MSE covers a few steps and reads low), the MSE over the first 10 steps, and the one-step MSE.
# Runs that log the held rollout (`evaluate.rollout_errors`) get a panel of it too: stopped rollouts counted over
# the whole horizon, against constant velocity's over the same whole horizon.
CURVE_PANELS = (("against_cv", "rollout MSE / constant velocity's, same steps (first {steps})"),
                ("held_against_cv", "whole rollout, stops held / constant velocity's (first {steps})"),
                ("mse_h10", "MSE over the first 10 steps (box units²)"), ("one_step_mse", "one-step MSE (box units²)"))
RATIOS = {"against_cv": ("rollout_mse", "baseline_cv_same_steps_mse"),
          "held_against_cv": ("rollout_mse_held", "baseline_cv_rollout_mse")}
# The physical diagnostics along training (gns_bench/evaluate/diagnostics.py), against steps: 1 is the truth's.
DIAGNOSTIC_PANELS = (("gravity_ratio", "gravity ratio, one step on true windows"),
                     ("held_gravity_ratio", "gravity ratio, one step held still (velocities 0)"),
                     ("held_fall_ratio", "held still and let go: fall over 10 steps / g's"),
                     ("rollout_gravity_ratio", "gravity ratio along the rollout"),
                     ("landing_ratio", "the floor's push on landing material, one step on true windows"),
                     ("com_fall_ratio", "centre-of-mass fall, ours / truth"))
DPI = 80


def curve(row: RunRow, metric: str) -> list[tuple[float, float]]:
    """(training seconds, value) of `step_points`' points, of a finished run or one still training (`collect`
    reads the curves)."""
    if row.record is None:
        return []
    seconds = dict(row.record.curves.get("curve/train_seconds", []))
    return [(seconds[step], value) for step, value in step_points(row, metric) if step in seconds]


def by_candidate(sweep: SweepSpec, rows: list[RunRow]) -> dict[str, list[RunRow]]:
    groups: dict[str, list[RunRow]] = {name: [] for name in sweep.candidates}
    for row in rows:
        groups.setdefault(row.planned.axes[CANDIDATE_AXIS], []).append(row)
    return {name: group for name, group in groups.items() if group}


def winner(groups: dict[str, list[RunRow]]) -> tuple[str, str]:
    """(the best candidate by its mean rollout MSE over constant velocity's on the same steps, a sentence on how
    clear its lead is against the seed spread)."""
    means = {name: mean_std([relative_to_cv(r) for r in group if r.ok]) for name, group in groups.items()}
    ranked = sorted((m for m in means.items() if m[1][2]), key=lambda item: item[1][0])
    if not ranked:
        return "", "No candidate has finished yet."
    best, (mean, std, seeds) = ranked[0]
    words = "Lowest rollout MSE against constant velocity's on the same steps"
    if len(ranked) == 1:
        return best, f"Only `{best}` has finished ({fmt(mean)}x)."
    runner_up, (mean2, std2, seeds2) = ranked[1]
    if seeds > 1 and seeds2 > 1:
        clear = mean + std < mean2 - std2
        verdict = "clear of the seed spread" if clear else "within the seed spread: not separated"
        return best, (f"{words}: `{best}` ({fmt(mean)}x ± {fmt(std)} over {seeds} seeds), against `{runner_up}` "
                      f"({fmt(mean2)}x ± {fmt(std2)} over {seeds2}), {verdict}.")
    return best, (f"{words}: `{best}` ({fmt(mean)}x), against `{runner_up}` ({fmt(mean2)}x); one seed of at least "
                  "one of them, so the lead is not yet measured against the seed spread.")


def candidates_table(groups: dict[str, list[RunRow]]) -> list[str]:
    header = ("| candidate | seeds | steps | training time (s) | s/step | one-step MSE | rollout MSE | vs constant "
              "velocity, same steps | whole rollout, stops held, vs constant velocity | MSE at 10 / 100 steps | "
              "rollout steps covered | hardware | MLflow runs |")
    lines = [header, "|" + "---|" * header.count(" | ") + "---|"]
    for name, group in groups.items():
        done = [r for r in group if r.ok]

        def mean(metric: str, done: list[RunRow] = done) -> float:
            return mean_std([r.metric(metric) for r in done])[0]
        rollout, rollout_std, seeds = mean_std([r.metric("rollout_mse") for r in done])
        cv, held = mean("baseline_cv_same_steps_mse"), mean("rollout_mse_held")
        cv_whole = mean("baseline_cv_rollout_mse")
        steps, seconds = mean("train/final_step"), mean("train/wall_time_s")
        cells = [f"`{name}`", str(seeds) if done else MISSING, fmt(steps), fmt(seconds) + shared_cores_mark(done),
                 fmt(seconds / steps) if steps else "—", fmt(mean("one_step_mse")),
                 mean_cell(rollout, rollout_std, seeds) if seeds else fmt(rollout),
                 f"{rollout / cv:.2g}x ({fmt(rollout)} / {fmt(cv)})" if cv > 0 else "—",
                 f"{held / cv_whole:.2g}x ({fmt(held)} / {fmt(cv_whole)})" if math.isfinite(held) and cv_whole > 0
                 else "—",
                 f"{fmt(mean('mse_h10'))} / {fmt(mean('mse_h100'))}",
                 steps_covered(done) if done else "—",
                 machines(done) or "—", run_ids_cell(group)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def diagnostics_table(groups: dict[str, list[RunRow]]) -> list[str]:
    """Each candidate's physical diagnostics on the test split (the domain table's columns): the mean over its
    seeds, each seed's value beside it where there are several; candidates with no finished run left out."""
    header = "| candidate | seeds | " + " | ".join(title for _, title in DIAGNOSTIC_COLUMNS) + " |"
    lines = [header, "|" + "---|" * (header.count(" | ") + 1)]
    for name, group in groups.items():
        done = [r for r in group if r.ok]
        if not done:
            continue
        cells = [f"`{name}`", str(len(done))]
        for metric, _ in DIAGNOSTIC_COLUMNS:
            values = [r.metric(metric) for r in done]
            known = len(values) > 1 and any(math.isfinite(v) for v in values)  # not logged by older runs: "—"
            seeds = f" ({' / '.join(fmt(v) for v in values)})" if known else ""
            cells.append(fmt(mean_std(values)[0]) + seeds)
        lines.append("| " + " | ".join(cells) + " |")
    return lines if len(lines) > 2 else []


def _panels_figure(groups: dict[str, list[RunRow]], panels: list[tuple[str, str]],
                   points_of: Callable[[RunRow, str], list[tuple[float, float]]], path: Path, *, xlabel: str,
                   x_unit: float = 1.0, style: Callable[[plt.Axes], None] = lambda ax: None) -> Path | None:
    """One panel per (metric, title) of `panels` that some run has points of (`points_of(row, metric)`: x, y),
    one line per run (a colour per candidate, further seeds dashed), x divided by `x_unit`; `style` finishes
    each panel. None when no run has any."""
    panels = [(metric, title) for metric, title in panels
              if any(points_of(row, metric) for group in groups.values() for row in group)]
    if not panels:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.2), squeeze=False)
    axes = axes[0]
    colours = plt.get_cmap("tab10")
    for index, (name, group) in enumerate(groups.items()):
        for seed_index, row in enumerate(group):
            for ax, (metric, _) in zip(axes, panels, strict=True):
                points = points_of(row, metric)
                if not points:
                    continue
                x, y = zip(*points, strict=True)
                ax.plot([value / x_unit for value in x], y, marker="o", ms=3, lw=1, color=colours(index % 10),
                        ls="-" if seed_index == 0 else "--", label=name if seed_index == 0 else None)
    for ax, (_, title) in zip(axes, panels, strict=True):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
        style(ax)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def curves_figure(groups: dict[str, list[RunRow]], path: Path, rollout_steps: int) -> Path | None:
    """Error against training time, one line per run (colour per candidate), one panel per metric some run
    logged."""
    return _panels_figure(groups, [(metric, label.format(steps=rollout_steps)) for metric, label in CURVE_PANELS],
                          curve, path, xlabel="training time (min)", x_unit=60.0,
                          style=lambda ax: ax.set_yscale("log"))


def _truth_lines(ax: plt.Axes) -> None:
    ax.axhline(1.0, color="black", lw=0.8, ls=":")  # the truth's
    ax.axhline(0.0, color="grey", lw=0.5)


def diagnostics_figure(groups: dict[str, list[RunRow]], path: Path) -> Path | None:
    """The physical diagnostics against training steps, one line per run, a panel for each diagnostic some
    run logged (runs from before one existed leave it out); None when no run logged any."""
    return _panels_figure(groups, list(DIAGNOSTIC_PANELS), step_points, path, xlabel="training steps",
                          style=_truth_lines)


GRAVITY_TOLERANCE = 0.1  # a block falls at g when its gravity ratio is within 10% of 1
FIT_FROM = 0.5  # the power law is fitted from half the last evaluated step on: the early transient left out


def step_points(row: RunRow, metric: str) -> list[tuple[float, float]]:
    """(step, value) of one `curve/<metric>` a run logged, or of a `RATIOS` ratio of two, finite values only."""
    if row.record is None:
        return []
    if metric in RATIOS:
        numerator, denominator = RATIOS[metric]
        baseline = dict(row.record.curves.get(f"curve/{denominator}", []))
        values = [(step, value / baseline[step]) for step, value in row.record.curves.get(f"curve/{numerator}", [])
                  if baseline.get(step, 0) > 0]
    else:
        values = row.record.curves.get(f"curve/{metric}", [])
    return [(step, value) for step, value in values if math.isfinite(value)]


def seconds_per_step(row: RunRow) -> float | None:
    """Training seconds a step at the run's last evaluated point (`curve/train_seconds`)."""
    points = row.record.curves.get("curve/train_seconds", []) if row.record else []
    return points[-1][1] / points[-1][0] if points and points[-1][0] > 0 else None


def settled_cell(row: RunRow, metric: str) -> str:
    """From which evaluated step a ratio whose truth is 1 (gravity's, the floor's push) stays within
    `GRAVITY_TOLERANCE` of 1, or how far it swings."""
    points = step_points(row, metric)
    if not points:
        return "—"
    step = settled_step(points, 1.0, GRAVITY_TOLERANCE)
    if step is not None:
        return f"from step {step:,.0f}"
    late = [v for s, v in points if s >= FIT_FROM * points[-1][0]]
    return (f"not by step {points[-1][0]:,.0f} (last {fmt(points[-1][1])}; {min(late):.2f} to {max(late):.2f} over "
            "the second half)")


# The ratios whose truth is 1 that the "when the blocks fall at g and land" tables follow along training.
SETTLING = ("gravity_ratio", "rollout_gravity_ratio", "landing_ratio")


def settled_cells(row: RunRow) -> str:
    """`settled_cell` of each of `SETTLING`, as table cells."""
    return " | ".join(settled_cell(row, metric) for metric in SETTLING)


def _prediction(fit: PowerLaw | None, paper: float | None, per_step: float | None,
                last: tuple[float, float]) -> tuple[str, str]:
    if fit is None:
        return "—", "—"
    interval = (f" ({fit.exponent_interval[0]:.2f} to {fit.exponent_interval[1]:.2f})"
                if fit.exponent_interval else "")
    law = f"{fit.exponent:.2f}{interval} over steps {fit.first_step:,.0f}-{fit.last_step:,.0f} ({fit.points} points)"
    if paper is None:
        return law, "no paper figure"
    if last[1] <= paper:
        return law, f"reached: {fmt(last[1])} at step {last[0]:,.0f}"
    if fit.exponent_interval is None:  # two points fit any line: no extrapolation without an interval
        return law, f"too few points to extrapolate ({fit.points}; the interval needs 3)"
    steps = fit.steps_to_reach(paper)
    if steps is None:
        return law, "no falling trend to extrapolate (the exponent, or its interval, reaches 0)"
    hours = f", {steps * per_step / 3600:,.0f} h at its {per_step:.2f} s/step" if per_step else ""
    return law, f"{steps:,.3g} steps{hours}"


# What the trend section fits: the paper's one-step MSE (Table 1 gives its figure) and the MSE over the first 10
# rollout steps, which every rollout reaches (on the cpu-tier data the one-step MSE flattens early while this
# one still falls: reports/study-gravity_curve), and, where a run logged it, the whole-rollout MSE with stopped
# rollouts held (`evaluate.rollout_errors`), the like-for-like of Table 1's rollout MSE.
TREND_METRICS = (("one_step_mse", "one-step MSE"), ("mse_h10", "MSE over rollout steps 1-10"),
                 ("rollout_mse_held", "whole-rollout MSE, stops held"))


def trend_section(groups: dict[str, list[RunRow]], domain: str, out_dir: Path) -> list[str]:
    """Where the curves go: for each run and `TREND_METRICS` metric a power law against steps and, for the
    one-step MSE, the budget it predicts for the paper's figure (Table 1); the step from which the gravity ratios
    stay within 10% of 1; and a log-log figure of the curves, their fits and the paper's figure."""
    rows = [row for group in groups.values() for row in group if step_points(row, "one_step_mse")]
    if not rows:
        return []
    reference = domain_reference(domain)
    paper = {"one_step_mse": reference.one_step_mse if reference else None,
             "rollout_mse_held": reference.rollout_mse if reference else None}
    header = ("| run | metric | evaluated to step | value there | exponent of steps (95% interval), fitted | steps "
              "to the paper's figure, predicted | hardware |")
    lines = ["## Where the curves go", "",
             f"Each error against training steps (on the validation trajectories the curve evaluates), with a power "
             f"law fitted by least squares in log-log from half the last evaluated step on (the early transient left "
             f"out); the one-step MSE's law extrapolated to the paper's one-step MSE for "
             f"{reference.name if reference else domain} ({fmt(paper['one_step_mse'])}, Table 1), and the "
             f"whole-rollout MSE's (a stopped rollout's particles held where the stop left them, to the end) to "
             f"its rollout MSE ({fmt(paper['rollout_mse_held'])}). The paper's "
             f"figure was measured on its own data: our solver's scenes are not its scenes, so the prediction says "
             f"where this curve's trend reaches that scale, not that it would reproduce the paper; an "
             f"extrapolation over a decade or more is a guess with the interval shown.", "",
             header, "|" + "---|" * header.count(" | ") + "---|"]
    fits: dict[tuple[str, str], PowerLaw | None] = {}
    for row in rows:
        for metric, label in TREND_METRICS:
            points = step_points(row, metric)
            if not points:
                continue
            fits[row.planned.name, metric] = fit = fit_power_law(points, FIT_FROM)
            law, prediction = _prediction(fit, paper.get(metric), seconds_per_step(row), points[-1])
            lines.append(f"| {row.planned.name} | {label} | {points[-1][0]:,.0f} | {fmt(points[-1][1])} | {law} | "
                         f"{prediction} | {machines([row]) or '—'} |")
    gravity = ["| run | gravity ratio within 10% of 1, true windows | along the rollout | floor's push, true windows |",
               "|---|---|---|---|"]
    gravity += [f"| {row.planned.name} | {settled_cells(row)} |" for row in rows]
    figure = trend_figure(rows, fits, paper, out_dir / "trend.png")
    return [*lines, "", f"![errors against steps and training time, log-log]({figure.name})", "",
            f"When the blocks fall at g and land: the first evaluated step from which each gravity ratio, and "
            f"the floor's push on landing material (`landing_ratio`), stays within {GRAVITY_TOLERANCE:.0%} of 1 "
            f"to the last point, or how far it still swings (its range over the second half of the curve; '—': "
            f"the run was evaluated before it was logged).", "", *gravity, "", *whole_rollouts_section(rows)]


WHOLE_SHARE = 0.8  # "whole rollouts": at least 4 of 5 reach the end without a monitor stopping them


def whole_points(row: RunRow) -> list[tuple[float, float, float]]:
    """(step, share of the curve's rollouts that reached the end, whole-rollout MSE with stops held over constant
    velocity's over the same whole horizon) at each evaluated step that logged both."""
    stopped = dict(step_points(row, "rollout_stopped"))
    ratio = dict(step_points(row, "held_against_cv"))
    return [(step, 1.0 - stopped[step], ratio[step]) for step in sorted(ratio) if step in stopped]


def whole_rollouts_section(rows: list[RunRow]) -> list[str]:
    """From which evaluated step each run's rollouts run whole: at least `WHOLE_SHARE` of them reach the end
    and their whole-rollout MSE (stops held) beats constant velocity's over the same horizon; the budget a cpu
    tier needs (none when no run logged the held rollout)."""
    measured = [(row, points) for row in rows if (points := whole_points(row))]
    if not measured:
        return []
    lines = ["Whole rollouts along training: the first evaluated step from which at least "
             f"{WHOLE_SHARE:.0%} of the curve's validation rollouts reach their end without a monitor stopping "
             "them and their whole-rollout MSE (a stopped rollout's particles held where the stop left them) stays "
             "below constant velocity's over the same horizon, at every later point; with the training time to "
             "that step on the run's hardware.", "",
             "| run | at the last point: reached the end, whole rollout vs constant velocity | whole from step | "
             "training time to it | hardware |", "|---|---|---|---|---|"]
    for row, points in measured:
        step, reached, ratio = points[-1]
        since = holds_from([(s, share >= WHOLE_SHARE and r < 1.0) for s, share, r in points])
        seconds = dict(row.record.curves.get("curve/train_seconds", []))
        hours = f"{seconds[since] / 3600:.2f} h" if since is not None and since in seconds else "—"
        lines.append(f"| {row.planned.name} | step {step:,.0f}: {reached:.0%}, {ratio:.2g}x | "
                     f"{f'{since:,.0f}' if since is not None else f'not by step {step:,.0f}'} | {hours} | "
                     f"{machines([row]) or '—'} |")
    return [*lines, ""]


def trend_figure(rows: list[RunRow], fits: dict[tuple[str, str], PowerLaw | None],
                 paper: dict[str, float | None], path: Path) -> Path:
    """Each `TREND_METRICS` error some run logged against steps and against training hours, log-log (a row of
    panels each), each run's fit dashed and the paper's figure (`paper`, by metric) dotted."""
    shown = [(metric, label) for metric, label in TREND_METRICS if any(step_points(row, metric) for row in rows)]
    fig, axes = plt.subplots(len(shown), 2, figsize=(9, 3.2 * len(shown)), squeeze=False)
    colours = plt.get_cmap("tab10")
    for (metric, label), (by_steps, by_time) in zip(shown, axes, strict=True):
        line_at = paper.get(metric)
        for index, row in enumerate(rows):
            points = [(step, value) for step, value in step_points(row, metric) if step > 0]  # log axes
            if not points:
                continue
            seconds = dict(row.record.curves.get("curve/train_seconds", []))
            colour = colours(index % 10)
            by_steps.plot(*zip(*points, strict=True), marker="o", ms=3, lw=1, color=colour, label=row.planned.name)
            timed = [(seconds[s] / 3600, v) for s, v in points if seconds.get(s, 0) > 0]
            if timed:
                by_time.plot(*zip(*timed, strict=True), marker="o", ms=3, lw=1, color=colour)
            fit, per_step = fits.get((row.planned.name, metric)), seconds_per_step(row)
            if fit is not None:
                reach = fit.steps_to_reach(line_at) if line_at else None
                line = np.geomspace(fit.first_step, min(reach, 100 * fit.last_step) if reach else 3 * fit.last_step)
                by_steps.plot(line, fit.value_at(line), color=colour, ls="--", lw=0.8)
                if per_step:
                    by_time.plot(line * per_step / 3600, fit.value_at(line), color=colour, ls="--", lw=0.8)
        for ax, x_label in ((by_steps, "training steps"), (by_time, "training time (h)")):
            if line_at:
                ax.axhline(line_at, color="black", ls=":", lw=1, label="paper (Table 1)" if ax is by_steps else None)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())  # decades only: minor labels overlap
            ax.set_xlabel(x_label)
            ax.set_ylabel(label, fontsize=8)
            ax.grid(alpha=0.3, which="both")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def unfinished_curves(rows: list[RunRow]) -> list[str]:
    """A sentence naming the runs whose curves end before their budget (still training, or stopped), with the
    last step each evaluated; none when every drawn curve is a finished run's."""
    parts = []
    for row in rows:
        points = row.record.curves.get("curve/train_seconds", []) if row.record else []
        if points and not row.ok:
            parts.append(f"{row.planned.name} ({row.status}, evaluated to step {points[-1][0]:,} of "
                         f"{row.planned.config.train.steps:,})")
    return [f"Not finished when this report was written, drawn as far as they went: {'; '.join(parts)}.", ""] \
        if parts else []


def candidates_section(sweep: SweepSpec, tier: str, rows: list[RunRow], out_dir: Path,
                       compare: bool = True) -> list[str]:
    """The study's table, its error-against-time figure and (`compare`: not at the smoke tier) its winner."""
    groups = by_candidate(sweep, rows)
    plan = rows[0].planned if rows else None
    tested_on = f"`{plan.domain}-{plan.evaluated_on}`" if plan else "—"
    rollout_steps = plan.config.train.eval_rollout_steps if plan else 0
    best, sentence = winner(groups)
    lines = ["## Candidates", "",
             f"Every candidate is scored on the same test trajectories ({tested_on}, split `test`): the paper's "
             "one-step and rollout MSE (the release's definitions), the rollout MSE against constant-velocity "
             "extrapolation over the same steps, the MSE over the first 10 and 100 steps, and the share of rollouts "
             "a health monitor stopped. Training time is the sum of step times (`train/wall_time_s`: stalls "
             "clipped, evaluation excluded).", "", *candidates_table(groups), ""]
    if compare:
        lines += [f"**Winner.** {sentence}", ""]
    if diagnostics := diagnostics_table(groups):
        lines += ["The same test trajectories' physical diagnostics, as the domain table gives them "
                  "(`gns_bench/evaluate/diagnostics.py`), mean over seeds with each seed's value in brackets: the "
                  "predicted acceleration of particles the truth has in free fall over g, on true windows and "
                  "held still (every input velocity 0: a block at rest in mid-air let go); how far such a block "
                  "falls in the model's first 10 steps over the fall at g; the gravity ratio along the model's own "
                  "rollout; the floor's push on landing material, one step on true windows, over the truth's; "
                  "the centre of mass's fall over the truth's; the share of particles through a wall; "
                  "the first step a monitor tripped. 1 is the truth for the ratios, 0 a block that hovers.", "",
                  *diagnostics, ""]
    figure = curves_figure(groups, out_dir / "error_vs_time.png", rollout_steps)
    if figure is not None:
        lines += ["## Error against training time", "",
                  f"Each run evaluated along the way on the first `train.eval_trajectories` validation trajectories "
                  f"(rolled out {rollout_steps} steps), against its training time so far; dashed: further seeds.", "",
                  f"![error against training time]({figure.name})", "", *unfinished_curves(rows)]
    diagnostics = diagnostics_figure(groups, out_dir / "diagnostics_vs_steps.png")
    if diagnostics is not None:
        lines += ["## Physical diagnostics against training steps", "",
                  "The same evaluations' physical diagnostics (`gns_bench/evaluate/diagnostics.py`): the predicted "
                  "acceleration of particles the truth has in free fall over g, on true windows and along the "
                  "model's own rollout, and how far the material's centre of mass falls over the truth's fall; "
                  "1 (dotted) is the truth, 0 a block that hovers.", "",
                  f"![physical diagnostics against training steps]({diagnostics.name})", "",
                  *(unfinished_curves(rows) if figure is None else [])]
    return lines + trend_section(groups, plan.domain, out_dir) if plan else lines


def gravity_studies_section(domain: str, tier: str, reports_root: Path) -> list[str]:
    """For a domain's report: each run of a study of the same domain that logged the gravity diagnostic along
    training (sweeps/studies/gravity_curve*.toml, the GOOP curves), from which step its blocks fall at g or how
    far its gravity ratio still swings, with a link to the study (none when no study logged it)."""
    lines = []
    for study in (load_sweep(path) for path in discover_sweeps()):
        if study.kind != "study" or study.domain != domain or tier not in study.tiers:
            continue
        for row in collect(study, tier, reports_root):
            if step_points(row, "gravity_ratio"):
                points = step_points(row, "gravity_ratio")
                lines.append(f"| [{study.name}](../../{study.name}/{tier}/README.md) | {row.planned.name} | "
                             f"{points[-1][0]:,.0f} | {settled_cells(row)} |")
    if not lines:
        return []
    return ["Along training, in the studies of this domain: the first evaluated step from which each gravity ratio, "
            f"and the floor's push on landing material, stays within {GRAVITY_TOLERANCE:.0%} of 1 to the last "
            "point, or how far it still swings.", "",
            "| study | run | evaluated to step | gravity ratio, true windows | along the rollout | floor's push |",
            "|---|---|---|---|---|---|", *lines, ""]
