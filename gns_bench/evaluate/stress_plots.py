"""One figure per stress test: its curves against the rollout step (log scale where they span decades), each
configuration (precision, scale factor) in the colour it has in every figure, ground truth dashed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gns_bench.evaluate.plots import GNS_LINE, MSE_UNIT, POSITION_UNIT, STEP_LABEL, TRUTH_LINE, config_colours
from gns_bench.evaluate.result import StressResult

# curve-name prefix -> (panel title, y label with its unit, log scale)
PANELS = {
    "mse": ("error against the ground truth", f"position MSE ({MSE_UNIT})", True),
    "divergence": ("divergence from the reference precision", f"RMS distance ({POSITION_UNIT})", True),
    "model_distance": ("growth of an initial perturbation", f"RMS distance ({POSITION_UNIT})", True),
    "solver_distance": ("growth of an initial perturbation", f"RMS distance ({POSITION_UNIT})", True),
    "rigidity_drift": ("rigid body: drift of pairwise distances", "relative change (dimensionless)", True),
}
PREFIXES = ("rigidity_drift", "model_distance", "solver_distance", "divergence", "mse")


def _panel(name: str) -> str:
    for prefix in PREFIXES:
        if name.startswith(prefix):
            return "model_distance" if prefix == "solver_distance" else prefix
    return name


def curve_label(name: str) -> tuple[str, bool]:
    """(the configuration a curve shows, whether it is the ground truth): `mse_fp32` -> ("fp32", False),
    `mse_x4` -> ("x4", False), `rigidity_drift_truth` and `solver_distance` -> ("ground truth", True), a
    prefix alone (`mse`, `model_distance`) -> ("GNS", False)."""
    if name.startswith("solver_distance"):
        return "ground truth", True
    prefix = next((p for p in PREFIXES if name.startswith(p)), "")
    rest = name[len(prefix):].strip("_") if prefix else name
    if rest == "truth":
        return "ground truth", True
    return rest or "GNS", False


def plot_stress(result: StressResult, path: str | Path, *, training_length: int | None = None,
                title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels: dict[str, list[str]] = {}
    for name in result.curves:
        panels.setdefault(_panel(name), []).append(name)
    colours = config_colours(curve_label(name)[0] for name in result.curves)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 3.4), squeeze=False, layout="constrained")
    for ax, (panel, names) in zip(axes[0], panels.items(), strict=True):
        heading, ylabel, log = PANELS.get(panel, (panel, panel, False))
        for name in names:
            y = np.asarray(result.curves[name], dtype=float)
            ok = np.isfinite(y) & ((y > 0) if log else True)
            label, truth = curve_label(name)
            if ok.any():
                ax.plot(np.flatnonzero(ok) + 1, y[ok], label=label, lw=1.2, c=colours[label],
                        ls=TRUTH_LINE if truth else GNS_LINE)
        if training_length:
            ax.axvline(training_length, color="grey", ls=":", lw=1, label="training length")
        if log:
            ax.set_yscale("log")
        ax.set_title(heading, fontsize=9)
        ax.set_xlabel(STEP_LABEL, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle(title or f"stress: {result.name}", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
