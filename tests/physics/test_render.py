"""Rendering: a PNG strip and a GIF per trajectory, 2D and 3D, coloured by particle type."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from gns_bench.data.format import PARTICLE_TYPE_COLOURS
from gns_bench.physics.render import render_dataset


def _has_colour(image: Image.Image, hex_colour: str, tolerance: int = 40) -> bool:
    rgb = np.asarray(image.convert("RGB")).reshape(-1, 3).astype(int)
    target = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])
    return bool(np.any(np.abs(rgb - target).sum(axis=1) < tolerance))


@pytest.mark.parametrize("domain, colours", [("waterramps", (5, 3)), ("multimaterial", (5,)), ("goop-3d", (7,))])
def test_render_writes_strip_and_animation(domain: str, colours: tuple[int, ...], tmp_path: Path,
                                           smoke_dataset: Callable[[str], Path]) -> None:
    png, gif = render_dataset(smoke_dataset(domain), split="test", traj=0, out=tmp_path / domain, frames=4)
    assert png == tmp_path / f"{domain}.png" and gif == tmp_path / f"{domain}.gif"
    strip = Image.open(png)
    assert strip.width > 3 * strip.height  # a horizontal strip of 4 frames
    for type_id in colours:
        assert _has_colour(strip, PARTICLE_TYPE_COLOURS[type_id]), f"no particles of type {type_id} drawn"
    animation = Image.open(gif)
    assert animation.n_frames >= 10


def test_render_rejects_missing_trajectory(smoke_dataset: Callable[[str], Path]) -> None:
    with pytest.raises(IndexError, match="no trajectory 7"):
        render_dataset(smoke_dataset("waterdrop"), split="test", traj=7)
