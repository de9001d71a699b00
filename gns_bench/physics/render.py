"""Render one trajectory of a dataset: a PNG strip of frames and an animated GIF, coloured by particle type.

2D datasets are drawn as scatter plots in their bounds; 3D ones as 3D scatter plots with the vertical axis
(the one gravity acts along, y in our specs) drawn upwards.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import matplotlib

matplotlib.use("Agg")  # files only, never a window (also on headless CI)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402

from gns_bench.data.format import PARTICLE_TYPE_NAMES, read_metadata, type_colour, type_colours  # noqa: E402

GIF_FRAMES = 40


def _read_trajectory(dataset_dir: Path, split: str, traj: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions [T, N, D], particle types [N] and birth frames [N] (zeros unless the data has inflow)."""
    path = dataset_dir / f"{split}.h5"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such split file")
    with h5py.File(path, "r") as f:
        keys = sorted(f.keys())
        key = f"{traj:05d}"
        if key not in f:
            raise IndexError(f"{path}: no trajectory {traj} (the split holds {len(keys)})")
        group = f[key]
        types = group["particle_type"][()]
        birth = group["birth_step"][()] if "birth_step" in group else np.zeros(len(types), np.int64)
        return group["position"][()].astype(np.float32), types, birth


def _vertical_axis(gravity: list[float] | None, dim: int) -> int:
    return int(np.argmax(np.abs(gravity))) if gravity and any(gravity) else dim - 1


def _draw(ax, frame: np.ndarray, types: np.ndarray, bounds: np.ndarray, up: int, size: float) -> None:
    colours = type_colours(types)
    if frame.shape[1] == 2:
        ax.scatter(frame[:, 0], frame[:, 1], c=colours, s=size, linewidths=0)
        ax.set_xlim(*bounds[0])
        ax.set_ylim(*bounds[1])
        ax.set_aspect("equal")
    else:
        # matplotlib's 3D z axis is drawn upwards: put the vertical (gravity) axis there
        horizontal = [d for d in range(3) if d != up]
        order = [horizontal[0], horizontal[1], up]
        ax.scatter(*(frame[:, d] for d in order), c=colours, s=size, linewidths=0, depthshade=True)
        for setter, d in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), order, strict=True):
            setter(*bounds[d])
        ax.set_box_aspect([bounds[d][1] - bounds[d][0] for d in order])
    ax.set_xticks([])
    ax.set_yticks([])
    if frame.shape[1] == 3:
        ax.set_zticks([])


def _axes(fig, dim: int, *grid: int):
    return fig.add_subplot(*grid, projection="3d") if dim == 3 else fig.add_subplot(*grid)


def render_dataset(dataset_dir: str | Path, split: str = "test", traj: int = 0, out: str | Path | None = None,
                   frames: int = 6) -> tuple[Path, Path]:
    """Write `<out>.png` (a strip of `frames` evenly spaced frames) and `<out>.gif`; return both paths.

    `out` defaults to `<dataset_dir>/render/<split>_<traj>`.
    """
    dataset_dir = Path(dataset_dir)
    meta = read_metadata(dataset_dir)
    position, types, birth = _read_trajectory(dataset_dir, split, traj)
    stem = Path(out) if out is not None else dataset_dir / "render" / f"{split}_{traj:05d}"
    stem.parent.mkdir(parents=True, exist_ok=True)
    png, gif = stem.with_suffix(".png"), stem.with_suffix(".gif")
    bounds = np.asarray(meta.bounds)
    up = _vertical_axis(meta.gravity, meta.dim)
    size = float(np.clip(3000.0 / max(len(types), 1), 0.3, 6.0))
    steps = len(position)

    fig = plt.figure(figsize=(2.2 * frames, 2.4), dpi=80)
    for k, t in enumerate(np.linspace(0, steps - 1, frames).round().astype(int)):
        ax = _axes(fig, meta.dim, 1, frames, k + 1)
        _draw(ax, position[t, birth <= t], types[birth <= t], bounds, up, size)  # inflow: born ones only
        ax.set_title(f"t={t}", fontsize=8)
    present = sorted(set(types.tolist()))
    handles = [plt.Line2D([], [], marker="o", ls="", color=type_colour(t),
                          label=PARTICLE_TYPE_NAMES.get(t, str(t))) for t in present]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=7, frameon=False)
    fig.suptitle(f"{meta.name or dataset_dir.name}  {split}[{traj}]", fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    fig.savefig(png)
    plt.close(fig)

    fig = plt.figure(figsize=(3.2, 3.2), dpi=70)
    ax = _axes(fig, meta.dim, 1, 1, 1)
    indices = np.linspace(0, steps - 1, min(GIF_FRAMES, steps)).round().astype(int)

    def update(t: int) -> None:
        ax.clear()
        _draw(ax, position[t, birth <= t], types[birth <= t], bounds, up, size)
        ax.set_title(f"{meta.name} t={t}", fontsize=8)

    FuncAnimation(fig, update, frames=indices).save(gif, writer=PillowWriter(fps=12))
    plt.close(fig)
    return png, gif
