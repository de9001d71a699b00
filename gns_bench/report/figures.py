"""Report figures: ablation panels (shaped like the paper's Fig. 4), time against error with its Pareto
front, rigid-body drift over a rollout (App. C.7), and rollouts (ground truth beside prediction) as PNG and
GIF. Every axis names its quantity and unit; a configuration has one colour in every figure
(`evaluate.plots.config_colours`). Small files: modest dpi."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import PillowWriter  # noqa: E402

from gns_bench.data.format import type_colours  # noqa: E402
from gns_bench.evaluate import metrics  # noqa: E402
from gns_bench.evaluate.plots import (  # noqa: E402
    AXIS_NAMES,
    GNS_LINE,
    MSE_UNIT,
    PALETTE,
    POSITION_UNIT,
    STEP_LABEL,
    STOP_COLOUR,
    TRUTH_LINE,
    VIEW_AXES,
    config_colours,
    config_label,
    frame_steps,
    plot_rollout,
    rollout_extent,
    stop_step,
    stop_text,
    type_legend_handles,
)
from gns_bench.evaluate.result import RolloutResult  # noqa: E402

DPI = 80
RIGIDITY_WORDS = ("the RMS change of the body's pairwise distances since the rollout began, relative to their "
                  "RMS; the model solid, ground truth dashed; 0 is perfectly rigid")
PANELS = (("one_step_mse", "one-step MSE"), ("rollout_mse", "rollout MSE"), ("ot", "optimal transport"),
          ("mmd", "MMD"))
# Where a health monitor stopped rollouts, the raw rollout MSE, OT and MMD cover different steps in different runs
# (a rollout that collapsed early reads low); these panels then compare the runs like for like, as the verdicts
# do (gns_bench/report/verdict.py).
STOPPED_PANELS = (("vs_cv", "vs constant velocity, same steps"),
                  ("rollout_steps", "rollout steps before a stop"))
PANEL_LABELS = dict(PANELS + STOPPED_PANELS)


def ablation_panels(stopped: bool) -> tuple[tuple[str, str], ...]:
    """The ablation figure's panels in order: `PANELS`, with `STOPPED_PANELS` after the raw rollout MSE where a
    monitor stopped rollouts."""
    return PANELS[:2] + STOPPED_PANELS + PANELS[2:] if stopped else PANELS
# y-axis label of each panel: the quantity and its unit (OT is W2^2, squared Euclidean cost; MMD is squared
# and dimensionless, a difference of mean kernel values)
PANEL_UNITS = {"one_step_mse": f"MSE ({MSE_UNIT})", "rollout_mse": f"MSE ({MSE_UNIT})",
               "ot": f"W₂² ({MSE_UNIT})", "mmd": "MMD² (dimensionless)",
               "vs_cv": "GNS / constant velocity (ratio)", "rollout_steps": "steps"}


def _spans_decades(data: np.ndarray) -> bool:
    """Log scale only pays off for positive data spread over more than a decade."""
    finite = data[np.isfinite(data)]
    return bool(finite.size and (finite > 0).all() and finite.max() / finite.min() > 10)


def _save(fig: plt.Figure, axes: Sequence[plt.Axes], path: Path) -> Path:
    """Legend on the first panel (when it has labelled lines), then a tight, small PNG."""
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def ablation_figure(axis: str, values: list[Any], stats: dict[str, list[tuple[float, float, int]]],
                    reference: dict[str, Any], path: Path) -> Path:
    """`draw_ablation`, saved as a PNG."""
    fig = draw_ablation(axis, values, stats, reference)
    return _save(fig, fig.axes, path)


def draw_ablation(axis: str, values: list[Any], stats: dict[str, list[tuple[float, float, int]]],
                  reference: dict[str, Any]) -> plt.Figure:
    """One panel per metric of `stats` (in its order; `PANEL_LABELS` names them) against the axis value; error
    bars = sample std over seeds; the paper's default as a dashed line. `stats[metric][i]` is (mean, std, seeds)
    for `values[i]`. Up to four panels make a row, as the paper's Fig. 4; more make two rows."""
    scale = reference.get("scale", "linear")
    numeric = scale != "category" and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    x = np.asarray(values, dtype=float) if numeric else np.arange(len(values), dtype=float)
    name = axis.split(".")[-1]
    # each value is a configuration: coloured as its runs (`<name>=<value>-seed<s>`) are in the other figures
    colours = config_colours([f"{name}={v}" for v in values])
    columns = len(stats) if len(stats) <= 4 else math.ceil(len(stats) / 2)
    rows = math.ceil(len(stats) / columns)
    fig, grid = plt.subplots(rows, columns, figsize=(3.0 * columns, 2.9 * rows), squeeze=False)
    for ax in grid.flat[len(stats):]:
        fig.delaxes(ax)
    for ax, (metric, at_values) in zip(grid.flat[:len(stats)], stats.items(), strict=True):
        label = PANEL_LABELS[metric]
        mean = np.array([s[0] for s in at_values])
        std = np.array([s[1] for s in at_values])
        ax.errorbar(x, mean, yerr=std, marker="", c="0.45", capsize=3, lw=1)
        ax.scatter(x, mean, s=24, c=[colours[f"{name}={v}"] for v in values], zorder=3, linewidths=0)
        if "default" in reference:
            default = reference["default"]
            where = (float(default) if numeric else
                     next((float(i) for i, v in enumerate(values) if str(v) == str(default)), None))
            if where is not None:
                ax.axvline(where, ls="--", c="k", lw=1, label="paper default")
        if numeric and scale == "log":
            positive = x[x > 0]
            if (x <= 0).any() and positive.size:
                ax.set_xscale("symlog", linthresh=float(positive.min()))
            elif positive.size == x.size:
                ax.set_xscale("log")
        if not numeric:
            ax.set_xticks(x, [str(v) for v in values])
        if _spans_decades(mean):
            ax.set_yscale("log")
        ax.margins(x=0.15)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel(name, fontsize=8)  # a configuration value: its unit is the config key's
        ax.set_ylabel(PANEL_UNITS[metric], fontsize=8)
        ax.tick_params(labelsize=7)
    return fig


def pareto_front(cost: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Indices of the points no other point beats on both cost and error (lower is better), by cost."""
    order = np.lexsort((error, cost))
    front, best = [], math.inf
    for i in order:
        if np.isfinite(cost[i]) and np.isfinite(error[i]) and error[i] < best:
            front.append(int(i))
            best = error[i]
    return np.asarray(front, dtype=int)


MAX_LEGEND_CONFIGS = 10  # more configurations than this: only the Pareto front's points are named


def time_error_figure(points: list[tuple[str, float, float, float]], path: Path) -> Path:
    """points: (label, training seconds, rollout seconds per step, rollout MSE), one per run; a run's colour
    is its configuration's (seeds of one configuration share it)."""
    fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.4))
    error = np.array([p[3] for p in points], dtype=float)
    colours = config_colours([p[0] for p in points])
    configs = list(dict.fromkeys(config_label(p[0]) for p in points))
    for ax, column, xlabel in ((axes[0], 1, "training wall time (s)"), (axes[1], 2, "rollout time per step (s)")):
        cost = np.array([p[column] for p in points], dtype=float)
        ax.scatter(cost, error, s=20, c=[colours[p[0]] for p in points], linewidths=0, zorder=3)
        front = pareto_front(cost, error)
        if front.size:
            ax.plot(cost[front], error[front], "-o", c="k", ms=6, lw=1, mfc="none", label="Pareto front")
        for i in front:
            ax.annotate(points[i][0], (cost[i], error[i]), fontsize=6, xytext=(3, 3), textcoords="offset points")
        if _spans_decades(cost):
            ax.set_xscale("log")
        if _spans_decades(error):
            ax.set_yscale("log")
        ax.margins(0.15)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(f"rollout MSE ({MSE_UNIT})", fontsize=8)
        ax.tick_params(labelsize=7)
    if len(configs) <= MAX_LEGEND_CONFIGS:  # the configurations, by colour, beside the Pareto front's entry
        by_config = {config_label(p[0]): colours[p[0]] for p in points}
        axes[1].legend(handles=[plt.Line2D([], [], marker="o", ls="", c=by_config[c], label=c) for c in configs],
                       fontsize=6, loc="best")
    return _save(fig, axes, path)




# ----------------------------------------------------------------------------------------------
# Rigid bodies (App. C.7): does the GNS keep BOXBATH's cube rigid, as the solver's shape matching does?
# ----------------------------------------------------------------------------------------------

def rigidity_curves(result: RolloutResult, rigid_type: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(model, ground truth) `metrics.rigidity_drift` of the particles of `rigid_type`, from the start of the
    rollout (the last input frame, step 0) to each step; None without a rigid body. The model's curve ends where
    a monitor stopped the rollout."""
    rigid = result.particle_type == rigid_type
    if result.birth_step is not None:  # inflow: only a body present from the start has a rest shape
        rigid &= result.birth_step < result.initial_window.shape[0]
    if rigid.sum() < 2:
        return None
    start = result.initial_window[-1:]
    return (metrics.rigidity_drift(np.concatenate([start, result.predicted]), rigid),
            metrics.rigidity_drift(np.concatenate([start, result.ground_truth]), rigid))


def rigidity_figure(rollouts: Sequence[RolloutResult], rigid_type: int, path: Path,
                    labels: Sequence[str] | None = None, max_trajectories: int = 8,
                    model: str = "GNS") -> Path | None:
    """Rigid-body drift against the rollout step, `model` (the architecture that rolled out) solid and ground truth
    dashed, one colour per trajectory (the first `max_trajectories` with a body of `rigid_type`); an x where a monitor
    stopped the model. None (no file) when no rollout has such a body. `labels[i]` names rollout i (default: trajectory
    i)."""
    curves = [(i, c) for i, r in enumerate(rollouts) if (c := rigidity_curves(r, rigid_type)) is not None]
    if not curves:
        return None
    shown = curves[:max_trajectories]
    fig, ax = plt.subplots(figsize=(5.6, 3.6), layout="constrained")
    series, stops = [], []
    handles = [plt.Line2D([], [], c="k", ls=GNS_LINE, label=model),
               plt.Line2D([], [], c="k", ls=TRUTH_LINE, label="ground truth")]
    for n, (i, (gns, truth)) in enumerate(shown):
        colour = PALETTE[n % len(PALETTE)]
        name = labels[i] if labels is not None else f"trajectory {i}"
        series.append((colour, gns, truth))
        if stop_step(rollouts[i]) is not None:
            stops.append((gns.size - 1, gns[-1]))
        handles.append(plt.Line2D([], [], c=colour, lw=3, label=name))
    values = np.concatenate([c for _, gns, truth in series for c in (gns[1:], truth[1:])])
    log = _spans_decades(values[values > 0])
    for colour, gns, truth in series:
        for curve, style, width in ((truth, TRUTH_LINE, 1.0), (gns, GNS_LINE, 1.3)):
            # step 0 is the reference itself (drift 0 by definition); a log scale cannot show 0 at all
            y = np.where(curve > 0, curve, np.nan) if log else curve
            ax.plot(np.arange(len(curve)), y, ls=style, c=colour, lw=width)
    if stops:
        ax.plot(*np.transpose(stops), marker="x", c=STOP_COLOUR, ms=7, mew=1.5, ls="")
        handles.insert(2, plt.Line2D([], [], marker="x", c=STOP_COLOUR, ls="", label="stopped by a monitor"))
    if log:
        ax.set_yscale("log")
    ax.set_xlabel(STEP_LABEL, fontsize=8)
    ax.set_ylabel("rigidity drift (fraction of rest distance)", fontsize=8)
    more = f" (first {len(shown)} of {len(curves)} trajectories)" if len(curves) > len(shown) else ""
    ax.set_title(f"rigid body: RMS |d_ij(t) − d_ij(0)| / RMS d_ij(0){more}", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, fontsize=6, loc="best", ncol=2)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------------
# Rollouts: ground truth beside the model, one frame for both, the stop and flagged steps marked
# ----------------------------------------------------------------------------------------------

def _thin(result: RolloutResult, max_particles: int = 5000) -> RolloutResult:
    """Every k-th particle, so pictures of 20k-particle 3D scenes stay small files (the stop kept)."""
    stride = max(1, -(-len(result.particle_type) // max_particles))
    if stride == 1:
        return result
    return dataclasses.replace(
        result, predicted=result.predicted[:, ::stride], ground_truth=result.ground_truth[:, ::stride],
        initial_window=result.initial_window[:, ::stride], particle_type=result.particle_type[::stride],
        birth_step=None if result.birth_step is None else result.birth_step[::stride])


def rollout_png(result: RolloutResult, path: Path, title: str, marks: dict[int, str] | None = None,
                model: str = "GNS") -> Path:
    """Ground truth and `model`'s prediction at 4 steps over the whole horizon (3D data seen from the side,
    `VIEW_AXES`), the step a monitor stopped the rollout and `marks` (step index -> label: where one flagged it)
    shown."""
    return plot_rollout(_thin(result), path, None, num_frames=4, title=title, marks=marks, name=model)


def rollout_strip(models: Sequence[tuple[str, RolloutResult]], path: Path, title: str) -> Path:
    """One test trajectory as each model rolled it out, a row per model below the ground truth, at the same
    steps (the first model's 4 evenly spaced ones and each model's last before a monitor stopped it); every
    rollout must be of the same trajectory."""
    (_, first), others = models[0], models[1:]
    for name, other in others:
        start, first_start = other.initial_window[-1], first.initial_window[-1]
        if start.shape != first_start.shape or not np.array_equal(start, first_start):
            raise ValueError(f"{path}: {name}'s rollout does not start where the {models[0][0]}'s does: not "
                             "the same test trajectory")
    return plot_rollout(_thin(first), path, None, num_frames=4, title=title, name=models[0][0],
                        others=[(name, _thin(other)) for name, other in others])


def rollout_gif(result: RolloutResult, path: Path, title: str, max_frames: int = 30, fps: int = 8,
                marks: dict[int, str] | None = None, model: str = "GNS") -> Path:
    """An animation: ground truth on the left, `model` on the right, in one frame, at most `max_frames` frames
    over the whole horizon; after a monitor stopped the rollout the model's panel says so, and the caption names the
    steps `marks` flagged once they are reached."""
    result = _thin(result)
    marks = dict(marks or {})
    steps = frame_steps(result, max_frames)
    dims = list(VIEW_AXES)
    limits = rollout_extent(result, (dims[0], dims[1]))
    colours = type_colours(result.particle_type)
    size = float(np.clip(3000.0 / len(result.particle_type), 1.0, 10.0))  # visible dots for small scenes too
    fig, axes = plt.subplots(1, 2, figsize=(5.0, 3.3), sharex=True, sharey=True, layout="constrained")
    scatters = []
    start = result.ground_truth[0][:, dims] if len(result.ground_truth) else result.initial_window[-1][:, dims]
    for ax, label in ((axes[0], "ground truth"), (axes[1], model)):
        scatters.append(ax.scatter(start[:, 0], start[:, 1], s=size, c=colours, linewidths=0))
        ax.set_xlim(limits[0])
        ax.set_ylim(limits[1])
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
        ax.set_title(label, fontsize=8)
        ax.set_xlabel(f"{AXIS_NAMES[dims[0]]} ({POSITION_UNIT})", fontsize=7)
    axes[0].set_ylabel(f"{AXIS_NAMES[dims[1]]} ({POSITION_UNIT})", fontsize=7)
    stopped = axes[1].text(0.5, 0.5, stop_text(result).replace(" (", "\n("), transform=axes[1].transAxes,
                           ha="center", va="center", fontsize=7, color=STOP_COLOUR, visible=False)
    fig.legend(handles=type_legend_handles(result.particle_type), loc="outside lower center",
               ncol=len(set(result.particle_type.tolist())), fontsize=6, frameon=False)
    caption = fig.suptitle(title, fontsize=8)

    def draw(i: int) -> list:
        step = steps[i]
        hidden = ~result.shown_at(step)  # inflow particles waiting to enter: NaN offsets are not drawn
        for scatter, frames in zip(scatters, (result.ground_truth, result.predicted), strict=True):
            if step < frames.shape[0]:
                xy = frames[step][:, dims].astype(float)
                xy[hidden] = np.nan
            else:  # past the stop (or the data): nothing to draw
                xy = np.full((len(result.particle_type), 2), np.nan)
            scatter.set_offsets(xy)
        stopped.set_visible(step >= result.predicted.shape[0])
        flagged = [f"{text} (step {s})" for s, text in sorted(marks.items()) if s <= step]
        caption.set_text(f"{title} - step {step + 1}" + ("\nflagged: " + "; ".join(flagged) if flagged else ""))
        return scatters

    # Frames written straight to the writer: FuncAnimation drew each frame twice (for the screen, then for the
    # file), and laying the figure out again every frame took half of each draw. The last frame's caption is the
    # longest, so the figure is laid out once, for it.
    draw(len(steps) - 1)
    fig.canvas.draw()
    fig.set_layout_engine("none")
    writer = PillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi=60):
        for i in range(len(steps)):
            draw(i)
            writer.grab_frame()
    plt.close(fig)
    return path
