"""Rollout pictures: one frame for ground truth and GNS, the stop and flagged steps marked, a legend of particle
types; the colour of a configuration the same in every figure."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.collections import PathCollection

from gns_bench.evaluate.plots import (
    POSITION_UNIT,
    config_colour,
    config_colours,
    draw_rollout,
    flag_marks,
    plot_rollout,
    stop_text,
)
from gns_bench.evaluate.result import RolloutResult

TRUTH_STEPS = 20


def synthetic_rollout(stopped_at: int | None = None, reason: str | None = None) -> RolloutResult:
    """A 2D scene of water (5), a rigid body (0) and a wall (3) drifting right; the GNS drifts faster and, when
    `stopped_at` is given, has only that many steps."""
    rng = np.random.default_rng(0)
    types = np.array([5] * 20 + [0] * 6 + [3] * 4)
    start = rng.uniform(0.2, 0.8, size=(len(types), 2)).astype(np.float32)
    steps = np.arange(1, TRUTH_STEPS + 1, dtype=np.float32)[:, None, None]
    truth = start + 0.005 * steps * np.array([1.0, 0.0], np.float32)
    predicted = start + 0.008 * steps * np.array([1.0, 0.0], np.float32)
    window = np.stack([start - 0.005 * i * np.array([1.0, 0.0], np.float32) for i in (2, 1, 0)])
    if stopped_at is not None:
        predicted = predicted[:stopped_at]
    return RolloutResult(predicted, truth, window, types, stopped_at, reason)


def _panels(fig: plt.Figure) -> list[plt.Axes]:
    """The scene panels: those with equal aspect (not the timeline)."""
    return [ax for ax in fig.axes if ax.get_aspect() == 1.0]


def _texts(fig: plt.Figure) -> list[str]:
    return [t.get_text() for ax in fig.axes for t in ax.texts]


def test_a_stopped_rollout_says_where_and_why_in_every_panel_after_the_stop(tmp_path: Path) -> None:
    result = synthetic_rollout(stopped_at=8, reason="energy_blowup at step 8: kinetic energy 12x the reference")
    assert stop_text(result) == "stopped at step 8 (energy_blowup)"  # 8 steps made, as the monitor says
    fig = draw_rollout(result, num_frames=4, title="worst")
    panels = _panels(fig)
    titles = [ax.get_title() for ax in panels if ax.get_title()]
    # evenly spaced over the whole horizon (20 steps), plus the last step before the stop
    assert titles == ["step 1", "step 7", "step 8", "step 14", "step 20"]
    gns = panels[1::2]
    drawn = [bool([c for c in ax.collections if isinstance(c, PathCollection)]) for ax in gns]
    assert drawn == [True, True, True, False, False]  # steps 14 and 20 come after the stop
    blank = [ax for ax in gns if ax.texts]
    assert [t.get_text().replace("\n", " ") for ax in blank for t in ax.texts] == \
        ["stopped at step 8 (energy_blowup)"] * 2
    assert any("stopped at step 8 (energy_blowup)" == text for text in _texts(fig))  # on the timeline too
    # one frame: every panel has the same limits, equal aspect; axes name the quantity and the unit
    assert len({(ax.get_xlim(), ax.get_ylim()) for ax in panels}) == 1
    assert all(POSITION_UNIT in ax.get_xlabel() for ax in gns)
    assert "ground truth" in panels[0].get_ylabel() and POSITION_UNIT in panels[0].get_ylabel()
    (legend,) = fig.legends
    assert sorted(t.get_text() for t in legend.get_texts()) == ["kinematic", "rigid", "water"]
    plt.close(fig)
    path = plot_rollout(result, tmp_path / "stopped.png", title="worst")
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.std() > 0


def test_a_rollout_read_back_from_npz_is_known_to_have_stopped() -> None:
    result = synthetic_rollout(stopped_at=5)
    result.stopped_at = None  # npz files keep no stop: a prediction shorter than its ground truth stopped
    assert stop_text(result) == "stopped at step 5 (health monitor)"
    assert stop_text(synthetic_rollout()) == ""


def test_flagged_steps_are_marked_from_the_step_on() -> None:
    fig = draw_rollout(synthetic_rollout(), num_frames=3, marks={9: "density_collapse"})
    texts = _texts(fig)
    assert "step 9: density_collapse" in texts  # the timeline
    assert texts.count("flagged: density_collapse (step 9)") == 2  # the GNS panels of steps 11 and 20, not 1
    assert not any(t.startswith("stopped") for t in texts)
    plt.close(fig)


def test_flag_marks_read_the_evaluation_tag() -> None:
    tag = ("trajectory 0: energy_blowup at step 12: kinetic energy 11x the reference, out_of_bounds at step 40: "
           "a particle is 0.2 outside the bounds (margin 0.03); trajectory 4: density_collapse at step 3: 5 pairs "
           "closer than 0.1 R, energy_blowup at step 3: ...")
    assert flag_marks(tag) == {0: {12: "energy_blowup", 40: "out_of_bounds"},
                               4: {3: "density_collapse, energy_blowup"}}
    assert flag_marks("") == {}


def test_a_configuration_has_one_colour_whatever_else_is_drawn() -> None:
    assert config_colour("noise_std=0.0003-seed0") == config_colour("noise_std=0.0003-seed4")
    labels = ["x1", "x2", "x4", "x8", "fp32", "GNS", "ground truth"]
    colours = config_colours(labels)
    assert len(set(colours.values())) == len(labels)  # no two configurations of a figure alike
    assert config_colours(reversed(labels)) == colours  # the order they come in does not matter
    seeds = config_colours(["a-seed0", "a-seed1", "b-seed0"])
    assert seeds["a-seed0"] == seeds["a-seed1"] != seeds["b-seed0"]


def test_an_empty_rollout_cannot_be_drawn() -> None:
    empty = RolloutResult(np.zeros((0, 3, 2)), np.zeros((0, 3, 2)), np.zeros((3, 3, 2)), np.array([5, 5, 5]))
    with pytest.raises(ValueError, match="empty rollout"):
        draw_rollout(empty)


def test_other_models_get_a_row_each_with_their_own_stop(tmp_path: Path) -> None:
    gns = synthetic_rollout()
    cconv = synthetic_rollout(stopped_at=5, reason="out_of_bounds at step 5: a particle left the box")
    dpi = synthetic_rollout()
    fig = draw_rollout(gns, num_frames=4, others=[("CConv", cconv), ("DPI-Net", dpi)])
    panels = _panels(fig)
    titles = [ax.get_title() for ax in panels if ax.get_title()]
    assert titles == ["step 1", "step 5", "step 7", "step 14", "step 20"]  # CConv's last step before its stop added
    labels = [ax.get_ylabel().split("\n")[0] for ax in panels if ax.get_ylabel()]
    assert labels == ["ground truth", "GNS", "CConv", "DPI-Net"]  # a row per model below the ground truth
    assert len(panels) == 4 * len(titles)
    cconv_row = panels[2::4]
    after_stop = [ax for ax, title in zip(cconv_row, titles, strict=True) if int(title.split()[1]) > 5]
    assert after_stop and all("stopped at step 5 (out_of_bounds)" in " ".join(t.get_text() for t in ax.texts)
                              .replace("\n", " ") for ax in after_stop)
    assert all(ax.collections for ax in panels[1::4] + panels[3::4])  # GNS and DPI ran the whole horizon
    assert "CConv: stopped at step 5 (out_of_bounds)" in _texts(fig)  # on the timeline, named
    plt.close(fig)


def test_the_model_row_is_named_for_the_architecture_that_rolled_out() -> None:
    fig = draw_rollout(synthetic_rollout(), num_frames=3, name="CConv")  # a baseline sweep's own pictures
    labels = [ax.get_ylabel().split("\n")[0] for ax in _panels(fig) if ax.get_ylabel()]
    assert labels == ["ground truth", "CConv"]
    plt.close(fig)
