"""A metric of one's own, registered once, is computed in evaluation, logged, and shown in the sweep's report."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from gns_bench.evaluate.registry import Metric, register_metric, unregister_metric
from gns_bench.report import report
from gns_bench.report.collect import collect
from gns_bench.sweep.runner import run_sweep
from gns_bench.sweep.spec import SWEEPS_DIR, load_sweep


def final_error(result) -> float:
    k = result.predicted.shape[0]
    return float(((result.predicted[-1] - result.ground_truth[k - 1]) ** 2).sum(-1).mean())


@pytest.fixture
def registered():
    metric = register_metric(Metric("final_error", final_error, "position units²",
                                    "squared distance to the truth at the rollout's last step, mean over particles"))
    yield metric
    unregister_metric(metric.name)


def test_a_registered_metric_reaches_the_report(registered: Metric, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    (tmp_path / "sweeps" / "domains").mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", tmp_path / "sweeps" / "tiers.toml")
    (tmp_path / "sweeps" / "domains" / "tiny.toml").write_text(
        'description = "tiny"\ndomain = "tiny"\n\n[tiers.smoke.config.model]\nlatent_size = 8\n'
        'mlp_hidden_size = 8\nmessage_passing_steps = 1\n')
    sweep = load_sweep(tmp_path / "sweeps" / "domains" / "tiny.toml")
    (outcome,) = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False)
    assert outcome.status == "FINISHED", outcome.error
    (row,) = collect(sweep, "smoke", tmp_path / "reports")
    logged = row.metric("final_error")  # `test/final_error` in MLflow: the mean over test trajectories
    assert np.isfinite(logged) and logged > 0
    page = report.write_sweep_report(sweep, "smoke", tmp_path / "reports" / sweep.name / "smoke").read_text()
    header = next(line for line in page.splitlines() if line.startswith("| run |"))
    assert header.rstrip(" |").endswith("final_error")
    assert f"| {logged:.3g} |" in next(line for line in page.splitlines() if line.startswith("| seed0 |"))
    assert "- **final_error** (position units²; lower is better): squared distance to the truth" in page
