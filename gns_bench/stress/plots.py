"""One figure per stress test: its curves against the rollout step (log scale where they span decades)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gns_bench.stress.result import StressResult

# curve-name prefix -> (panel title, y label, log scale)
PANELS = {
    "mse": ("error against the ground truth", "position MSE", True),
    "divergence": ("divergence from the reference precision", "RMS distance", True),
    "model_distance": ("growth of an initial perturbation", "RMS distance", True),
    "solver_distance": ("growth of an initial perturbation", "RMS distance", True),
    "rigidity_drift": ("rigid body: largest pairwise-distance change", "relative change", True),
}


def _panel(name: str) -> str:
    for prefix in ("rigidity_drift", "model_distance", "solver_distance", "divergence", "mse"):
        if name.startswith(prefix):
            return "model_distance" if prefix == "solver_distance" else prefix
    return name


def plot_stress(result: StressResult, path: str | Path, *, training_length: int | None = None,
                title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels: dict[str, list[str]] = {}
    for name in result.curves:
        panels.setdefault(_panel(name), []).append(name)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 3.4), squeeze=False)
    for ax, (panel, names) in zip(axes[0], panels.items(), strict=True):
        heading, ylabel, log = PANELS.get(panel, (panel, panel, False))
        for name in names:
            y = np.asarray(result.curves[name], dtype=float)
            ok = np.isfinite(y) & ((y > 0) if log else True)
            if ok.any():
                ax.plot(np.flatnonzero(ok) + 1, y[ok], label=name.replace("_", " "), lw=1.2)
        if training_length:
            ax.axvline(training_length, color="grey", ls=":", lw=1, label="training length")
        if log:
            ax.set_yscale("log")
        ax.set(title=heading, xlabel="rollout step", ylabel=ylabel)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle(title or f"stress: {result.name}", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
