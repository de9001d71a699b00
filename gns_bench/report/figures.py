"""Report figures: ablation panels (shaped like the paper's Fig. 4), time against error with its Pareto
front, and rollouts (ground truth beside prediction) as PNG and GIF. Small files: modest dpi."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402

from gns_bench.data.format import type_colours  # noqa: E402
from gns_bench.evaluate.plots import VIEW_AXES, plot_rollout  # noqa: E402
from gns_bench.evaluate.result import RolloutResult  # noqa: E402

DPI = 80
PANELS = (("one_step_mse", "one-step MSE"), ("rollout_mse", "rollout MSE"), ("ot", "optimal transport"),
          ("mmd", "MMD"))


def _spans_decades(data: np.ndarray) -> bool:
    """Log scale only pays off for positive data spread over more than a decade."""
    finite = data[np.isfinite(data)]
    return bool(finite.size and (finite > 0).all() and finite.max() / finite.min() > 10)


def _save(fig: plt.Figure, axes: Sequence[plt.Axes], path: Path) -> Path:
    """Legend on the first panel, then a tight, small PNG."""
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
    """One panel per metric against the axis value; error bars = std over seeds; the paper's default as a
    dashed line. `stats[metric][i]` is (mean, std, seeds) for `values[i]`."""
    scale = reference.get("scale", "linear")
    numeric = scale != "category" and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    x = np.asarray(values, dtype=float) if numeric else np.arange(len(values), dtype=float)
    fig, axes = plt.subplots(1, len(PANELS), figsize=(3.0 * len(PANELS), 2.8))
    for ax, (metric, label) in zip(axes, PANELS, strict=True):
        mean = np.array([s[0] for s in stats[metric]])
        std = np.array([s[1] for s in stats[metric]])
        ax.errorbar(x, mean, yerr=std, marker="o", capsize=3, lw=1)
        if "default" in reference:
            default = reference["default"]
            where = (float(default) if numeric else
                     next((float(i) for i, v in enumerate(values) if str(v) == str(default)), None))
            if where is not None:
                ax.axvline(where, ls="--", c="tab:red", lw=1, label="paper default")
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
        ax.set_xlabel(axis.split(".")[-1], fontsize=8)
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


def time_error_figure(points: list[tuple[str, float, float, float]], path: Path) -> Path:
    """points: (label, training seconds, rollout seconds per step, rollout MSE), one per run."""
    fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.2))
    error = np.array([p[3] for p in points], dtype=float)
    for ax, column, xlabel in ((axes[0], 1, "training wall time (s)"), (axes[1], 2, "rollout time per step (s)")):
        cost = np.array([p[column] for p in points], dtype=float)
        ax.scatter(cost, error, s=18, c="tab:blue", label="runs")
        front = pareto_front(cost, error)
        if front.size:
            ax.plot(cost[front], error[front], "-o", c="tab:red", ms=4, lw=1, mfc="none", label="Pareto front")
        for i in front:
            ax.annotate(points[i][0], (cost[i], error[i]), fontsize=6, xytext=(3, 3), textcoords="offset points")
        if _spans_decades(cost):
            ax.set_xscale("log")
        if _spans_decades(error):
            ax.set_yscale("log")
        ax.margins(0.15)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel("rollout MSE", fontsize=8)
        ax.tick_params(labelsize=7)
    return _save(fig, axes, path)


def _extent(result: RolloutResult, dims: tuple[int, int]) -> list[list[float]]:
    """Plot limits from the ground truth, with a margin: predictions that fly off show as leaving the box."""
    frames = np.concatenate([result.initial_window, result.ground_truth])[..., list(dims)]
    lo, hi = frames.reshape(-1, 2).min(0), frames.reshape(-1, 2).max(0)
    pad = 0.05 * float(max(hi - lo)) + 1e-6
    return [[float(lo[0] - pad), float(hi[0] + pad)], [float(lo[1] - pad), float(hi[1] + pad)]]


def _thin(result: RolloutResult, max_particles: int = 5000) -> RolloutResult:
    """Every k-th particle, so pictures of 20k-particle 3D scenes stay small files."""
    stride = max(1, -(-len(result.particle_type) // max_particles))
    if stride == 1:
        return result
    return RolloutResult(result.predicted[:, ::stride], result.ground_truth[:, ::stride],
                         result.initial_window[:, ::stride], result.particle_type[::stride],
                         birth_step=None if result.birth_step is None else result.birth_step[::stride])


def rollout_png(result: RolloutResult, path: Path, title: str) -> Path:
    """Ground truth and prediction at 4 steps (3D data seen from the side, `VIEW_AXES`)."""
    result = _thin(result)
    dims = VIEW_AXES
    limits = _extent(result, dims)
    bounds = [[0.0, 1.0]] * result.predicted.shape[2]
    bounds[dims[0]], bounds[dims[1]] = limits[0], limits[1]
    return plot_rollout(result, path, bounds, num_frames=4, title=title)


def rollout_gif(result: RolloutResult, path: Path, title: str, max_frames: int = 30, fps: int = 8) -> Path:
    """An animation: ground truth on the left, GNS on the right, at most `max_frames` frames."""
    result = _thin(result)
    k = min(result.predicted.shape[0], result.ground_truth.shape[0])
    if k == 0:
        raise ValueError("empty rollout: nothing to animate")
    steps = np.unique(np.linspace(0, k - 1, min(max_frames, k)).round().astype(int))
    dims = list(VIEW_AXES)
    limits = _extent(result, (dims[0], dims[1]))
    colours = type_colours(result.particle_type)
    size = float(np.clip(3000.0 / len(result.particle_type), 1.0, 10.0))  # visible dots for small scenes too
    fig, axes = plt.subplots(1, 2, figsize=(5.0, 2.8))
    scatters = []
    start = result.ground_truth[0][:, dims]  # placeholders; `draw` sets every frame's points
    for ax, label in ((axes[0], "ground truth"), (axes[1], "GNS")):
        scatters.append(ax.scatter(start[:, 0], start[:, 1], s=size, c=colours, linewidths=0))
        ax.set_xlim(limits[0])
        ax.set_ylim(limits[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(label, fontsize=8)
    caption = fig.suptitle(title, fontsize=8)

    def draw(i: int) -> list:
        step = steps[i]
        hidden = ~result.shown_at(step)  # inflow particles waiting to enter: NaN offsets are not drawn
        for scatter, frames in zip(scatters, (result.ground_truth, result.predicted), strict=True):
            xy = frames[step][:, dims].astype(float)
            xy[hidden] = np.nan
            scatter.set_offsets(xy)
        caption.set_text(f"{title} - step {step + 1}")
        return scatters

    animation = FuncAnimation(fig, draw, frames=len(steps), blit=False)
    animation.save(path, writer=PillowWriter(fps=fps), dpi=60)
    plt.close(fig)
    return path
