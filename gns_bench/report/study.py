"""Reports of studies that compare named candidates (`[candidates]` sweeps, e.g. sweeps/studies/cpu_budget.toml):
a table of every candidate on the same test trajectories, and error against training time from the curves the
runs logged along the way (`train.eval_every`: `curve/<metric>` at each evaluated step, with
`curve/train_seconds`). The winner is the candidate with the lowest rollout MSE at the end of its budget, mean
over seeds, named only when its seeds' spread keeps it clear of the runner-up."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from gns_bench.report.cells import (  # noqa: E402
    MISSING,
    fmt,
    machines,
    mean_cell,
    relative_to_cv,
    run_ids_cell,
    shared_cores_mark,
    steps_covered,
)
from gns_bench.report.collect import RunRow, mean_std  # noqa: E402
from gns_bench.sweep.spec import CANDIDATE_AXIS, SweepSpec  # noqa: E402

# What the error-against-time figure draws: the rollout MSE over constant velocity's on the same steps (like for
# like however early a monitor stopped a rollout; an untrained model's rollouts stop at once, so its raw rollout
# MSE covers a few steps and reads low), the MSE over the first 10 steps, and the one-step MSE.
CURVE_PANELS = (("against_cv", "rollout MSE / constant velocity's, same steps (first {steps})"),
                ("mse_h10", "MSE over the first 10 steps (box units²)"), ("one_step_mse", "one-step MSE (box units²)"))
# The physical diagnostics along training (gns_bench/evaluate/diagnostics.py), against steps: 1 is the truth's.
DIAGNOSTIC_PANELS = (("gravity_ratio", "gravity ratio, one step on true windows"),
                     ("rollout_gravity_ratio", "gravity ratio along the rollout"),
                     ("com_fall_ratio", "centre-of-mass fall, ours / truth"))
DPI = 80


def curve(row: RunRow, metric: str) -> list[tuple[float, float]]:
    """(training seconds, value) of one `curve/<metric>` a run logged, by step (`collect` reads the curves), of a
    finished run or one still training."""
    if row.record is None:
        return []
    seconds = dict(row.record.curves.get("curve/train_seconds", []))
    if metric == "against_cv":
        baseline = dict(row.record.curves.get("curve/baseline_cv_same_steps_mse", []))
        values = [(step, value / baseline[step]) for step, value in row.record.curves.get("curve/rollout_mse", [])
                  if baseline.get(step, 0) > 0]
    else:
        values = row.record.curves.get(f"curve/{metric}", [])
    return [(seconds[step], value) for step, value in values if step in seconds and math.isfinite(value)]


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
              "velocity, same steps | MSE at 10 / 100 steps | rollout steps covered | hardware | MLflow runs |")
    lines = [header, "|" + "---|" * header.count(" | ") + "---|"]
    for name, group in groups.items():
        done = [r for r in group if r.ok]

        def mean(metric: str, done: list[RunRow] = done) -> float:
            return mean_std([r.metric(metric) for r in done])[0]
        rollout, rollout_std, seeds = mean_std([r.metric("rollout_mse") for r in done])
        cv = mean("baseline_cv_same_steps_mse")
        steps, seconds = mean("train/final_step"), mean("train/wall_time_s")
        cells = [f"`{name}`", str(seeds) if done else MISSING, fmt(steps), fmt(seconds) + shared_cores_mark(done),
                 fmt(seconds / steps) if steps else "—", fmt(mean("one_step_mse")),
                 mean_cell(rollout, rollout_std, seeds) if seeds else fmt(rollout),
                 f"{rollout / cv:.2g}x ({fmt(rollout)} / {fmt(cv)})" if cv > 0 else "—",
                 f"{fmt(mean('mse_h10'))} / {fmt(mean('mse_h100'))}",
                 steps_covered(done) if done else "—",
                 machines(done) or "—", run_ids_cell(group)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def curves_figure(groups: dict[str, list[RunRow]], path: Path, rollout_steps: int) -> Path | None:
    """Error against training time, one line per run (colour per candidate), one panel per metric."""
    fig, axes = plt.subplots(1, len(CURVE_PANELS), figsize=(4.2 * len(CURVE_PANELS), 3.2))
    drawn = False
    colours = plt.get_cmap("tab10")
    for index, (name, group) in enumerate(groups.items()):
        for seed_index, row in enumerate(group):
            for ax, (metric, _) in zip(axes, CURVE_PANELS, strict=True):
                points = curve(row, metric)
                if not points:
                    continue
                drawn = True
                x, y = zip(*points, strict=True)
                ax.plot([t / 60 for t in x], y, marker="o", ms=3, lw=1, color=colours(index % 10),
                         ls="-" if seed_index == 0 else "--", label=name if seed_index == 0 else None)
    if not drawn:
        plt.close(fig)
        return None
    for ax, (_, label) in zip(axes, CURVE_PANELS, strict=True):
        ax.set_title(label.format(steps=rollout_steps), fontsize=9)
        ax.set_xlabel("training time (min)")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def diagnostics_figure(groups: dict[str, list[RunRow]], path: Path) -> Path | None:
    """The physical diagnostics against training steps, one line per run; None when no run logged them."""
    fig, axes = plt.subplots(1, len(DIAGNOSTIC_PANELS), figsize=(4.2 * len(DIAGNOSTIC_PANELS), 3.2))
    drawn = False
    colours = plt.get_cmap("tab10")
    for index, (name, group) in enumerate(groups.items()):
        for seed_index, row in enumerate(group):
            for ax, (metric, _) in zip(axes, DIAGNOSTIC_PANELS, strict=True):
                points = [(step, value) for step, value in (row.record.curves.get(f"curve/{metric}", [])
                                                            if row.record else []) if math.isfinite(value)]
                if not points:
                    continue
                drawn = True
                x, y = zip(*points, strict=True)
                ax.plot(x, y, marker="o", ms=3, lw=1, color=colours(index % 10),
                        ls="-" if seed_index == 0 else "--", label=name if seed_index == 0 else None)
    if not drawn:
        plt.close(fig)
        return None
    for ax, (_, label) in zip(axes, DIAGNOSTIC_PANELS, strict=True):
        ax.axhline(1.0, color="black", lw=0.8, ls=":")
        ax.axhline(0.0, color="grey", lw=0.5)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("training steps")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
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
    return lines
