"""The stability report and `gns-bench stress`, on a stress sweep over the tiny domain. It has no dataset
variants: `horizon` falls back to the test split, `scale` is skipped and the report says so."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import matplotlib.image
import mlflow
import pytest

from gns_bench import tracking
from gns_bench.cli import main
from gns_bench.report.report import write_sweep_report
from gns_bench.report.stability import write_stability_report
from gns_bench.sweep.runner import run_sweep, summarise_finished
from gns_bench.sweep.spec import SWEEPS_DIR, load_sweep

STRESS = '''description = "tiny stress"
domain = "tiny"
paper_figure = "Sec. 5.3"

[config.stress]
tests = ["precision", "horizon", "scale"]
scales = [2]
'''
STRESS_TIER = '''
[tiers.smoke.config.stress]
rollout_steps = 6
max_trajectories = 1
'''


@pytest.fixture(scope="module")
def stressed(tmp_path_factory: pytest.TempPathFactory, smoke_model: str) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("stability")
    (root / "sweeps" / "stress").mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", root / "sweeps" / "tiers.toml")
    path = root / "sweeps" / "stress" / "tiny.toml"
    path.write_text(STRESS + smoke_model + STRESS_TIER)
    outcomes = run_sweep(load_sweep(path), "smoke", data_root=root / "data", runs_root=root / "runs",
                         progress=False, echo=lambda _: None)
    assert [o.status for o in outcomes] == ["FINISHED"], [o.error for o in outcomes]
    # The same without a horizon test: the report bounds the horizon from the test evaluation's rollouts.
    short = root / "sweeps" / "stress" / "tiny_precision.toml"
    short.write_text(path.read_text().replace('tests = ["precision", "horizon", "scale"]', 'tests = ["precision"]'))
    assert [o.status for o in run_sweep(load_sweep(short), "smoke", data_root=root / "data",
                                        runs_root=root / "runs", progress=False, echo=lambda _: None)] == ["FINISHED"]
    return {"sweep": path, "short": short, "root": root, "run_id": outcomes[0].run_id}


def test_stress_results_are_logged_with_the_training_run(stressed: dict[str, Path]) -> None:
    tracking.configure()
    run = mlflow.get_run(stressed["run_id"])
    metrics, tags = run.data.metrics, run.data.tags
    assert metrics["stress/precision/divergence_final_fp32"] < metrics["stress/precision/divergence_final_bf16"]
    assert "scale x2: no dataset variant 'tiny-x2'" in tags["stress/skipped"]
    assert tags["stress/tests"] == "precision,horizon"
    assert metrics["stress/horizon/steps"] == 6 and metrics["stress/horizon/stable_steps"] <= 6


def test_stability_page_and_stress_report_show_tests_skips_and_figures(stressed: dict[str, Path], tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    sweep = load_sweep(stressed["sweep"])
    missing = load_sweep(SWEEPS_DIR / "stress" / "boxbath.toml")  # never run in this store: shown as missing
    text = write_stability_report("smoke", tmp_path / "stability" / "smoke", [sweep, missing]).read_text()
    row = next(line for line in text.splitlines() if line.startswith(f"| {sweep.name} | tiny |"))
    assert re.search(r"\| \d\S*x \(\d+ of 6 steps, [^)]*\) \| not run \|", row), row
    assert f"| {missing.name} | boxbath | **missing** |" in text and f"`{stressed['run_id']}`" in text
    # The page sums up and links; the figures live in each sweep's own report, drawn once (issue #20.6).
    assert f"[{sweep.name}](../../{sweep.name}/smoke/README.md)" in text and "![" not in text
    report = tmp_path / sweep.name / "smoke"
    summarise_finished(sweep, "smoke", tmp_path, [r.name for r in sweep.plan("smoke")])  # the runner's record
    readme = write_sweep_report(sweep, "smoke", report)
    text = readme.read_text()
    assert "no dataset variant 'tiny-x2'" in text
    assert "no variant 'tiny-long': rolled out the test split over its own length" in text
    figures = [f for f in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text) if f.startswith(sweep.name)]
    assert figures == [f"{sweep.name}_precision.png", f"{sweep.name}_horizon.png"]
    for figure in figures:
        image = matplotlib.image.imread(report / figure)
        assert min(image.shape[:2]) > 100 and image.std() > 0
    # Once the MLflow store is gone, the run summary beside the report writes it again, byte for byte.
    drawn = {p.name: p.read_bytes() for p in report.iterdir()}
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'empty.db'}")
    assert write_sweep_report(sweep, "smoke", report).read_text() == text
    assert {p.name: p.read_bytes() for p in report.iterdir()} == drawn


def test_without_a_horizon_test_the_evaluation_rollouts_bound_the_horizon(stressed: dict[str, Path],
                                                                          tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    sweep = load_sweep(stressed["short"])
    page = tmp_path / "stability" / "smoke"
    text = write_stability_report("smoke", page, [sweep]).read_text()
    # Its report and the page, written again from the run summary once the store is gone, say the same.
    summarise_finished(sweep, "smoke", tmp_path, [r.name for r in sweep.plan("smoke")])  # the runner's record
    report = write_sweep_report(sweep, "smoke", tmp_path / sweep.name / "smoke").read_text()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'empty.db'}")
    assert write_sweep_report(sweep, "smoke", tmp_path / sweep.name / "smoke").read_text() == report
    assert write_stability_report("smoke", page, [sweep]).read_text() == text
    monkeypatch.undo()
    row = next(line for line in text.splitlines() if line.startswith(f"| {sweep.name} | tiny |"))
    # the smoke tier's evaluation rolls out 10 steps (sweeps/tiers.toml)
    cell = r"\| \d+ of 10 steps of the 1 test rollout \(evaluation cut at 10 steps\), ([^|]*)\| ([^|]*) \|"
    match = re.search(cell, row)
    assert match, row
    unstable = match.group(1).startswith("a monitor stopped") or "flagged" in match.group(1)
    assert match.group(2).startswith("none: unstable") if unstable else match.group(2) == "not run", row


def test_stress_command(stressed: dict[str, Path], capsys: pytest.CaptureFixture) -> None:
    run_dir = next((stressed["root"] / "runs").rglob("checkpoint.pt")).parent
    dataset = stressed["root"] / "data" / "tiny-smoke-s0"
    code = main(["stress", str(run_dir), str(dataset), 'stress.tests=["precision"]', "stress.rollout_steps=4",
                 'stress.precisions=["fp32","bf16"]', "--experiment", "stress-cli"])
    out = capsys.readouterr().out
    assert code == 0 and "stress/precision/divergence_final_bf16" in out
    runs = mlflow.search_runs(experiment_names=["stress-cli"], output_format="list")
    assert [r.data.tags["kind"] for r in runs] == ["stress"]
    assert main(["stress", str(run_dir), str(dataset), "model.latent_size=4"]) == 2
    assert main(["stress", str(run_dir), str(dataset), 'stress.tests=["bogus"]']) == 2


class _Row:
    """The part of a RunRow that `stable_cells` reads when the horizon test ran."""

    def __init__(self, **metrics: float):
        self.metrics = metrics

    def metric(self, name: str) -> float:
        return self.metrics.get(name.removeprefix("stress/").replace("/", "_"), float("nan"))


def test_scale_cell_says_none_when_the_model_is_unstable_at_the_training_scale() -> None:
    from gns_bench.report.stability import stable_cells

    # stopped by a monitor at step 44 of 1200, within the training length of 150: no scale can be stable
    horizon, scale = stable_cells(_Row(horizon_stable_steps=44, horizon_training_length=150, horizon_steps=1200))
    assert horizon.startswith("0.29x (44 of 1200 steps, a monitor stopped it") and scale.startswith("none: unstable")
    # a horizon test cut at 6 steps that nothing stopped says nothing about scale
    horizon, scale = stable_cells(_Row(horizon_stable_steps=6, horizon_training_length=150, horizon_steps=6))
    assert "no monitor tripped" in horizon and scale == "not run"
    # a scale test that ran is reported as such
    _, scale = stable_cells(_Row(horizon_stable_steps=44, horizon_training_length=150, horizon_steps=1200,
                                 scale_largest_stable_factor=0.0))
    assert scale == "none stable"


def test_a_flagged_evaluation_rollout_is_not_a_stable_horizon(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without a horizon test, whole evaluation rollouts that a monitor flagged (it tripped, they ran on)
    do not make the horizon >= 1x."""
    from gns_bench.report import stability

    class Row(_Row):
        artifact_run_id, split = "r", "test"

        def param(self, name: str, default: str = "") -> str:
            return "None"

    monkeypatch.setattr(stability, "_rollout_lengths", lambda run_id, split: (5, 395, 395))
    horizon, unstable = stability._evaluation_horizon(Row())
    assert horizon.startswith(">= 1x") and not unstable
    horizon, unstable = stability._evaluation_horizon(Row(rollout_flagged=1.0))
    assert horizon.startswith("< 1x") and "flagged" in horizon and unstable


def test_a_stopped_evaluation_horizon_counts_the_rollouts_a_monitor_stopped(monkeypatch: pytest.MonkeyPatch) -> None:
    """The horizon is the shortest rollout's, and the cell says how many of the rollouts a monitor stopped
    (logged as the fraction of them), not "one" whatever the count."""
    from gns_bench.report import stability

    class Row(_Row):
        artifact_run_id, split = "r", "test"

        def param(self, name: str, default: str = "") -> str:
            return "None"

    monkeypatch.setattr(stability, "_rollout_lengths", lambda run_id, split: (5, 60, 995))
    horizon, unstable = stability._evaluation_horizon(Row(rollout_stopped=0.6))
    assert horizon.startswith("0.06x (the shortest ran 60 of 995 steps of the 5 test rollouts, "
                              "a monitor stopped 3 of 5;") and unstable
