"""Where a learning curve goes (report/trend.py): closed forms."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gns_bench.report.trend import fit_power_law, settled_step


def test_settled_step_is_where_the_curve_stays_within_the_band() -> None:
    curve = [(0, -2.0), (2000, 0.95), (4000, 1.3), (6000, 1.05), (8000, 0.98)]
    assert settled_step(curve) == 6000  # 0.95 at 2,000 left the band at 4,000
    assert settled_step(curve, tolerance=0.35) == 2000
    assert settled_step([*curve, (10000, 0.5)]) is None  # the last point is outside: not settled
    assert settled_step([(0, 1.0), (5, float("nan"))]) is None  # a NaN point is not within the band
    assert settled_step([]) is None
    assert settled_step(list(reversed(curve))) == 6000  # by step, whatever the order given


def test_a_power_law_is_recovered_and_extrapolated() -> None:
    steps = np.array([1000, 2000, 4000, 8000, 16000, 32000])
    exact = [(float(s), 3e-5 * s ** -0.5) for s in steps]
    fit = fit_power_law(exact, from_fraction=0.0)
    assert fit.exponent == pytest.approx(-0.5) and fit.scale == pytest.approx(3e-5)
    assert fit.points == 6 and fit.exponent_interval[0] == pytest.approx(-0.5)
    assert fit.steps_to_reach(3e-5 * 1e6 ** -0.5) == pytest.approx(1e6)
    assert fit.steps_to_reach(1.0) is None  # reached already
    late = fit_power_law(exact)  # from half the last step: 16,000 and 32,000
    assert late.points == 2 and late.exponent_interval is None and late.first_step == 16000

    rng = np.random.default_rng(0)
    noisy = [(float(s), 3e-5 * s ** -0.5 * math.exp(rng.normal(0, 0.1))) for s in steps]
    fit = fit_power_law(noisy, from_fraction=0.0)
    low, high = fit.exponent_interval
    assert low < -0.5 < high and high < 0 and fit.steps_to_reach(1e-9) > 32000


def test_a_flat_curve_predicts_nothing() -> None:
    rng = np.random.default_rng(1)
    flat = [(float(s), 9e-9 * math.exp(rng.normal(0, 0.2))) for s in range(2000, 22000, 2000)]
    fit = fit_power_law(flat)
    assert fit.exponent_interval[0] < 0 < fit.exponent_interval[1]
    assert fit.steps_to_reach(1.5e-9) is None
    assert fit_power_law([(0, 1.0), (10, -1.0)]) is None  # nothing positive at a positive step


def test_whole_rollouts_are_read_from_the_curve_only_where_they_hold_to_the_end() -> None:
    from types import SimpleNamespace

    from gns_bench import tracking
    from gns_bench.report.collect import RunRow
    from gns_bench.report.study import whole_rollouts_section

    steps = [0, 5000, 10000, 15000, 20000]
    stopped = [1.0, 0.25, 0.0, 0.5, 0.0]  # share of the 4 validation rollouts a monitor stopped
    held = [9.0, 0.8, 0.6, 0.7, 0.5]  # whole-rollout MSE with stops held; constant velocity's is 1
    curves = {"curve/rollout_stopped": list(zip(steps, stopped, strict=True)),
              "curve/rollout_mse_held": list(zip(steps, held, strict=True)),
              "curve/baseline_cv_rollout_mse": [(s, 1.0) for s in steps],
              "curve/train_seconds": [(s, 0.5 * s) for s in steps]}
    record = tracking.RunRecord("id", "recipe-seed0", "RUNNING", 0, tags={"hardware": "AMD EPYC, 1 thread"},
                                curves=curves)
    row = RunRow(SimpleNamespace(name="recipe-seed0"), record)
    [line] = [line for line in whole_rollouts_section([row]) if line.startswith("| recipe-seed0")]
    # 10,000 qualifies, but half the rollouts stop at 15,000: whole from 20,000 on, 10,000 s = 2.78 h of training
    assert line == "| recipe-seed0 | step 20,000: 100%, 0.5x | 20,000 | 2.78 h | AMD EPYC, 1 thread |"
    curves["curve/rollout_mse_held"][-1] = (20000, 1.2)  # worse than constant velocity at the last point
    [line] = [line for line in whole_rollouts_section([row]) if line.startswith("| recipe-seed0")]
    assert "| not by step 20,000 | — |" in line


def test_a_domain_report_says_where_its_gravity_studies_got(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The WATERDROP report carries the gravity study's verdict on its blocks (from the committed run summary, no
    MLflow store): each run, how far it was evaluated, and that g is not yet learned within 10%."""
    from gns_bench.report.study import gravity_studies_section

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'empty.db'}")
    reports = Path(__file__).resolve().parents[2] / "reports"
    lines = gravity_studies_section("waterdrop", "cpu", reports)
    rows = {row.split(" | ")[1]: row for row in lines if row.startswith("| [study-gravity_curve]")}
    for name in ("candidate=release-sampler-seed0", "candidate=start-share-seed0"):
        assert "| 30,000 | not by step 30,000" in rows[name]
    assert not any("goop" in line for line in lines)  # another domain's studies stay in their own report


def test_no_budget_is_extrapolated_from_two_points() -> None:
    from gns_bench.report.study import _prediction

    two = fit_power_law([(32000.0, 0.47), (33000.0, 0.11)], 0.5)  # a steep fall over an anneal's two points
    assert two is not None and two.exponent_interval is None
    _, prediction = _prediction(two, 0.0173, 0.6, (33000.0, 0.11))
    assert prediction == "too few points to extrapolate (2; the interval needs 3)"


def test_the_diagnostics_figure_draws_a_panel_for_each_diagnostic_some_run_logged(tmp_path: Path) -> None:
    """Runs from before a diagnostic existed leave its panel out rather than an empty frame; no run with any
    diagnostic, no figure."""
    from types import SimpleNamespace

    import matplotlib.image

    from gns_bench import tracking
    from gns_bench.report.collect import RunRow
    from gns_bench.report.study import DIAGNOSTIC_PANELS, DPI, diagnostics_figure

    def row(curves: dict) -> RunRow:
        return RunRow(SimpleNamespace(name="r"), tracking.RunRecord("id", "r", "FINISHED", 0, curves=curves))

    older = row({"curve/gravity_ratio": [(0, 0.1), (2000, 0.9)], "curve/rollout_gravity_ratio": [(2000, 0.5)]})
    newer = row({f"curve/{name}": [(2000, 0.8)] for name, _ in DIAGNOSTIC_PANELS})

    def panels(groups: dict) -> int:
        path = diagnostics_figure(groups, tmp_path / "figure.png")
        return round(matplotlib.image.imread(path).shape[1] / (4.2 * DPI))  # each panel 4.2 inches wide

    assert panels({"old": [older]}) == 2
    assert panels({"old": [older], "new": [newer]}) == len(DIAGNOSTIC_PANELS)
    assert diagnostics_figure({"none": [row({"curve/one_step_mse": [(0, 1e-8)]})]}, tmp_path / "none.png") is None
