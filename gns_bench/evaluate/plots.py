"""Pictures of rollouts: ground truth above, prediction below, at a few steps."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gns_bench.data.format import type_colours  # noqa: E402
from gns_bench.evaluate.result import RolloutResult  # noqa: E402

# Rollout pictures plot the x and y axes. In 2D that is the whole scene. In 3D it is a side view: every 3D
# domain generated here has gravity along -y, so particles falling or leaking through the floor stay
# visible (a view down the y axis would hide them).
VIEW_AXES = (0, 1)


def plot_rollout(result: RolloutResult, path: str | Path, bounds: list[list[float]] | None = None,
                 num_frames: int = 4, title: str = "") -> Path:
    """A 2 x num_frames grid; 3D data is shown from the side (`VIEW_AXES`)."""
    k = min(result.predicted.shape[0], result.ground_truth.shape[0])
    if k == 0:
        raise ValueError("empty rollout: nothing to plot")
    steps = np.unique(np.linspace(0, k - 1, num_frames).round().astype(int))
    colours = np.array(type_colours(result.particle_type))
    axes_dims = VIEW_AXES
    fig, axes = plt.subplots(2, len(steps), figsize=(2.4 * len(steps), 5.0), squeeze=False)
    for column, step in enumerate(steps):
        for row, (label, frames) in enumerate((("ground truth", result.ground_truth),
                                               ("GNS", result.predicted))):
            ax = axes[row, column]
            shown = result.shown_at(step)  # inflow: particles waiting to enter are hidden
            xy = frames[step][shown][:, axes_dims]
            ax.scatter(xy[:, 0], xy[:, 1], s=2, c=colours[shown], linewidths=0)
            if bounds is not None:
                ax.set_xlim(bounds[axes_dims[0]])
                ax.set_ylim(bounds[axes_dims[1]])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"step {step + 1}", fontsize=9)
            if column == 0:
                ax.set_ylabel(label, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
