"""Pictures of rollouts (ground truth above, the model below, at a few steps, one axis frame for all panels), and
the conventions every gns-bench figure shares: units on axes, one colour per configuration."""

from __future__ import annotations

import re
import zlib
from collections.abc import Iterable, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from gns_bench.data.format import PARTICLE_TYPE_NAMES, type_colour, type_colours  # noqa: E402
from gns_bench.evaluate.result import RolloutResult  # noqa: E402

# Rollout pictures plot the x and y axes. In 2D that is the whole scene. In 3D it is a side view: every 3D
# domain generated here has gravity along -y, so particles falling or leaking through the floor stay
# visible (a view down the y axis would hide them).
VIEW_AXES = (0, 1)
AXIS_NAMES = "xyz"

# Units on every axis. Positions are in the dataset's coordinates, where the box spans about [0, 1].
POSITION_UNIT = "box units"
MSE_UNIT = "box units²"
STEP_LABEL = "rollout step"
GNS_LINE, TRUTH_LINE = "-", "--"  # in curves over a rollout: the model solid, the ground truth dashed
STOP_COLOUR, FLAG_COLOUR = "#c0392b", "#e67e22"

PALETTE = tuple(plt.get_cmap("tab10").colors)


def config_label(label: str) -> str:
    """The configuration a run label names: `noise_std=0.0003-seed1` -> `noise_std=0.0003` (seeds of one
    configuration share its colour)."""
    return re.sub(r"-seed\d+$", "", str(label))


def config_colour(label: str) -> tuple[float, float, float]:
    """The colour of a configuration in every figure: a stable hash (CRC-32, not Python's salted `hash`) of
    its name, seed suffix dropped, into tab10. Ten colours: two configurations of one figure can share one,
    so figures name configurations in legends or labels too."""
    return PALETTE[zlib.crc32(config_label(label).encode()) % len(PALETTE)]


def config_colours(labels: Iterable[str]) -> dict[str, tuple[float, float, float]]:
    """A colour for each label of one figure: its configuration's `config_colour`, unless another configuration
    of the set took that colour first (in sorted order), then the next free one. A set of configurations gets
    the same colours in every figure (a sweep report's figures show one set); labels of one configuration
    (seeds) share a colour; beyond ten configurations colours repeat."""
    labels = list(labels)
    configs = sorted({config_label(label) for label in labels},
                     key=lambda c: (zlib.crc32(c.encode()) % len(PALETTE), c))
    taken: dict[str, int] = {}
    for config in configs:
        slot = zlib.crc32(config.encode()) % len(PALETTE)
        if len(taken) < len(PALETTE):
            while slot in taken.values():
                slot = (slot + 1) % len(PALETTE)
        taken[config] = slot
    return {label: PALETTE[taken[config_label(label)]] for label in labels}


def type_legend_handles(particle_type: Iterable[int]) -> list[Line2D]:
    """One legend entry per particle type present, in the type colours of every gns-bench picture."""
    present = sorted({int(t) for t in particle_type})
    return [Line2D([], [], marker="o", ls="", ms=5, color=type_colour(t), label=PARTICLE_TYPE_NAMES.get(t, f"type {t}"))
            for t in present]


def rollout_extent(result: RolloutResult, dims: tuple[int, int] = VIEW_AXES) -> list[list[float]]:
    """Plot limits [[x0, x1], [y0, y1]] from the ground truth, with a margin: predictions that fly off show as
    leaving the frame."""
    frames = np.concatenate([result.initial_window, result.ground_truth])[..., list(dims)].reshape(-1, 2)
    frames = frames[np.isfinite(frames).all(1)]
    lo, hi = frames.min(0), frames.max(0)
    pad = 0.05 * float(max(hi - lo)) + 1e-6
    return [[float(lo[0] - pad), float(hi[0] + pad)], [float(lo[1] - pad), float(hi[1] + pad)]]


def stop_step(result: RolloutResult) -> int | None:
    """The rollout step index (0-based, as `RolloutResult.stopped_at`) whose prediction a monitor rejected, or
    None. Rollouts read back from npz files keep no `stopped_at`: a prediction shorter than its ground truth
    is one that was stopped there."""
    if result.stopped_at is not None:
        return int(result.stopped_at)
    k = result.predicted.shape[0]
    return k if k < result.ground_truth.shape[0] else None


def stop_text(result: RolloutResult) -> str:
    """`stopped at step k (reason)`, k as monitors and reports count: k steps were predicted (the panel
    "step k" is the last one drawn) and the next one tripped the monitor; the reason is the monitor's name."""
    step = stop_step(result)
    if step is None:
        return ""
    reason = (getattr(result.stopped_by, "monitor", None)
              or re.sub(r" at step \d+.*$", "", result.stop_reason or "", flags=re.DOTALL) or "health monitor")
    return f"stopped at step {step} ({reason})"


def flag_marks(tag: str) -> dict[int, dict[int, str]]:
    """The `marks` of each trajectory from an evaluation's `<split>/rollouts_flagged` tag ("trajectory 3:
    energy_blowup at step 12: ..., out_of_bounds at step 40: ...; trajectory 5: ..."): trajectory -> {step:
    monitor}. Rollout npz files keep where a monitor stopped a rollout, not where one flagged it: the tag does."""
    marks: dict[int, dict[int, str]] = {}
    parts = re.split(r"(?:^|; )trajectory (\d+): ", tag or "")
    for index, text in zip(parts[1::2], parts[2::2], strict=True):
        for match in re.finditer(r"(\w+) at step (\d+)", text):
            steps = marks.setdefault(int(index), {})
            step = int(match.group(2))
            steps[step] = f"{steps[step]}, {match.group(1)}" if step in steps else match.group(1)
    return marks


def frame_steps(result: RolloutResult, num_frames: int) -> np.ndarray:
    """Step indices to draw: evenly spaced over the whole horizon, plus the last step a stopped rollout made."""
    total = max(result.predicted.shape[0], result.ground_truth.shape[0])
    if total == 0:
        raise ValueError("empty rollout: nothing to plot")
    steps = set(np.linspace(0, total - 1, num_frames).round().astype(int).tolist())
    stop = stop_step(result)
    if stop:  # the model's last frame before the stop, so the strip shows what the model did last
        steps.add(stop - 1)
    return np.asarray(sorted(steps), dtype=int)


def _frame(frames: np.ndarray, step: int) -> np.ndarray | None:
    return frames[step] if step < frames.shape[0] else None


def _blank(ax: plt.Axes, text: str, colour: str) -> None:
    ax.set_facecolor("#f4f4f4")
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=7, color=colour, wrap=True)


def draw_timeline(ax: plt.Axes, total: int, steps: Iterable[int], stops: Sequence[tuple[int, str]],
                  marks: dict[int, str]) -> None:
    """A strip of the whole rollout: the drawn steps (ticks at step index + 1, as the panels are titled), the
    stops (red: step, label; one per model drawn) and flagged steps (orange). A monitor "at step s" judged the
    prediction after step s: it is drawn between steps s and s + 1."""
    ax.set_xlim(0.5, total + 0.5)
    ax.set_ylim(0, 1)
    ax.set_yticks([])
    for step in steps:
        ax.axvline(step + 1, ymax=0.45, c="grey", lw=1)
    for i, (stop, stop_label) in enumerate(sorted(stops)):
        ax.axvspan(stop + 0.5, total + 0.5, color=STOP_COLOUR, alpha=0.15 / len(stops), lw=0)
        ax.axvline(stop + 0.5, c=STOP_COLOUR, lw=1.5)
        ax.text(stop + 0.5, 0.55 - 0.25 * i, stop_label, color=STOP_COLOUR, fontsize=7,
                ha="right" if stop > total / 2 else "left")
    for step, label in sorted(marks.items()):
        ax.plot([step + 0.5], [0.8], marker="v", c=FLAG_COLOUR, ms=6)
        ax.annotate(f"step {step}: {label}", (step + 0.5, 0.8), xytext=(4, -3), textcoords="offset points",
                    fontsize=6, color=FLAG_COLOUR, ha="left" if step < total / 2 else "right")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel(STEP_LABEL, fontsize=8)
    ax.tick_params(labelsize=7)
    for side in ("left", "right", "top"):
        ax.spines[side].set_visible(False)


def draw_rollout(result: RolloutResult, bounds: list[list[float]] | None = None, num_frames: int = 4,
                 title: str = "", marks: dict[int, str] | None = None,
                 others: Sequence[tuple[str, RolloutResult]] = (), name: str = "GNS") -> plt.Figure:
    """Ground truth above the model (`name`: the architecture that rolled `result` out) at `num_frames` steps over the
    whole horizon, all panels in one frame (equal aspect, the same limits: `bounds` per dimension, else the ground
    truth's extent); below, a timeline of the rollout with the step where a monitor stopped it and `marks` (step ->
    label, steps as monitors count them: `RolloutResult.stopped_at`, "energy_blowup at step 12"; e.g. where a monitor
    flagged a rollout that ran on). A model's panels after its stop say so. `others`: (name, rollout) of other models on
    the same trajectory, one row each below the first (the baselines' side-by-side strips), their stops on the timeline
    too. 3D data is seen from the side (`VIEW_AXES`)."""
    marks = dict(marks or {})
    models = [(name, result), *others]
    # evenly spaced steps, and the last step each model made before a monitor stopped it
    steps = sorted(set(frame_steps(result, num_frames).tolist()) | {s - 1 for _, r in others if (s := stop_step(r))})
    total = max(max(r.predicted.shape[0] for _, r in models), result.ground_truth.shape[0])
    dims = VIEW_AXES
    limits = ([bounds[dims[0]], bounds[dims[1]]] if bounds is not None else rollout_extent(result, dims))
    colours = np.array(type_colours(result.particle_type))
    size = float(np.clip(3000.0 / max(len(result.particle_type), 1), 1.0, 8.0))
    columns, rows = len(steps), [("ground truth", result.ground_truth, None), *((n, r.predicted, r) for n, r in models)]
    aspect = (limits[1][1] - limits[1][0]) / max(limits[0][1] - limits[0][0], 1e-9)  # a panel's height / width
    row_height = float(np.clip(2.1 * aspect + 0.5, 1.2, 2.8))  # no blank band between rows of a flat scene
    fig = plt.figure(figsize=(2.3 * columns + 0.6, row_height * len(rows) + 0.6), layout="constrained")
    grid = fig.add_gridspec(len(rows) + 1, columns, height_ratios=[1] * len(rows) + [0.28])
    first = None
    for column, step in enumerate(steps):
        for row, (label, frames, model) in enumerate(rows):
            ax = fig.add_subplot(grid[row, column], sharex=first, sharey=first)
            first = first or ax
            frame = _frame(frames, step)
            if frame is not None:
                shown = result.shown_at(step)  # inflow: particles waiting to enter are hidden
                xy = frame[shown][:, dims]
                ax.scatter(xy[:, 0], xy[:, 1], s=size, c=colours[shown], linewidths=0)
            elif model is not None and stop_step(model) is not None:
                _blank(ax, stop_text(model).replace(" (", "\n("), STOP_COLOUR)
            else:
                _blank(ax, f"no {label} frame", "grey")
            ax.set_xlim(limits[0])
            ax.set_ylim(limits[1])
            ax.set_aspect("equal")
            ax.tick_params(labelsize=6)
            flagged = [f"{text} (step {s})" for s, text in sorted(marks.items()) if s <= step]
            if model is result and flagged and frame is not None:
                ax.text(0.02, 0.98, "flagged: " + "; ".join(flagged), transform=ax.transAxes, va="top",
                        fontsize=6, color=FLAG_COLOUR)
            if row == 0:
                ax.set_title(f"step {step + 1}", fontsize=9)
            if row < len(rows) - 1:
                ax.tick_params(labelbottom=False)
            else:
                ax.set_xlabel(f"{AXIS_NAMES[dims[0]]} ({POSITION_UNIT})", fontsize=7)
            if column == 0:
                ax.set_ylabel(f"{label}\n{AXIS_NAMES[dims[1]]} ({POSITION_UNIT})", fontsize=8)
            else:
                ax.tick_params(labelleft=False)
    stops = [(step, stop_text(r) if not others else f"{name}: {stop_text(r)}")
             for name, r in models if (step := stop_step(r)) is not None]
    draw_timeline(fig.add_subplot(grid[len(rows), :]), total, steps, stops, marks)
    fig.legend(handles=type_legend_handles(result.particle_type), loc="outside lower center",
               ncol=len(set(result.particle_type.tolist())), fontsize=7, frameon=False, title="particle type",
               title_fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def plot_rollout(result: RolloutResult, path: str | Path, bounds: list[list[float]] | None = None,
                 num_frames: int = 4, title: str = "", marks: dict[int, str] | None = None,
                 others: Sequence[tuple[str, RolloutResult]] = (), name: str = "GNS") -> Path:
    """`draw_rollout`, saved as a PNG."""
    fig = draw_rollout(result, bounds, num_frames, title, marks, others, name)
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
