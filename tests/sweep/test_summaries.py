"""Run summaries as the runner writes them: one record per run name, merged as runs finish, written whole."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from gns_bench.report.kept import KEPT_FILE, read_kept, write_kept
from gns_bench.sweep.summaries import read_run_summary, record_runs
from gns_bench.tracking import RunRecord


def record(name: str, mse: float, status: str = "FINISHED") -> RunRecord:
    return RunRecord(f"id-{name}-{mse}", name, status, 1, {"model.latent_size": "8"},
                     {"rollout_mse": mse, "one_step_mse": math.nan}, {"tier": "smoke"},
                     {"curve/rollout_mse": [(10, mse), (20, mse / 2)]})


def test_runs_are_merged_by_name_and_only_finished_ones_are_kept(tmp_path: Path) -> None:
    path = tmp_path / "sweep" / "smoke" / "runs.json"
    assert record_runs(path, "sweep", "smoke", [record("a", 1.0), record("b", 2.0, "FAILED")]) == ["a"]
    assert list(read_run_summary(path)) == ["a"]
    written = path.read_bytes()
    # the same record again (a NaN metric, curves read back as lists) changes nothing
    assert record_runs(path, "sweep", "smoke", [record("a", 1.0)]) == []
    assert path.read_bytes() == written
    assert record_runs(path, "sweep", "smoke", [record("c", 3.0)]) == ["c"]
    assert record_runs(path, "sweep", "smoke", [record("a", 0.5)]) == ["a"]  # a newer run of the same name
    held = read_run_summary(path)
    assert sorted(held) == ["a", "c"] and held["a"].metrics["rollout_mse"] == 0.5 and held["c"].run_id == "id-c-3.0"
    assert held["a"].curves["curve/rollout_mse"] == [(10, 0.5), (20, 0.25)]
    assert [p.name for p in path.parent.iterdir()] == ["runs.json"]  # no temporary file left behind


def test_a_write_that_fails_leaves_the_summary_as_it_was(tmp_path: Path) -> None:
    path = tmp_path / "runs.json"
    record_runs(path, "sweep", "smoke", [record("a", 1.0)])
    before = path.read_bytes()
    broken = record("b", 2.0)
    broken.params = {"model.latent_size": object()}  # not JSON
    with pytest.raises(TypeError):
        record_runs(path, "sweep", "smoke", [broken])
    assert path.read_bytes() == before


def test_a_summary_written_by_older_code_keeps_the_report_s_data(tmp_path: Path) -> None:
    """Before the runner wrote the summaries, the report kept what it drew in the summary's `extras`: they
    are read from there until the report keeps its own file, and carried over when the runner adds a run."""
    path = tmp_path / "runs.json"
    picks = {"rollouts": {"run_id": "x", "shown": []}}
    path.write_text(json.dumps({"sweep": "s", "tier": "smoke", "note": "old", "runs": [], "extras": picks}))
    assert read_kept(tmp_path) == picks
    record_runs(path, "s", "smoke", [record("a", 1.0)])
    assert read_kept(tmp_path) == picks and list(read_run_summary(path)) == ["a"]
    assert write_kept(tmp_path, "s", "smoke", {}) is None and not (tmp_path / KEPT_FILE).exists()  # nothing to keep
    write_kept(tmp_path, "s", "smoke", {"rollouts": {"run_id": "y"}})
    assert read_kept(tmp_path) == {"rollouts": {"run_id": "y"}}  # the report's own file first
    write_kept(tmp_path, "s", "smoke", {})  # a file there is replaced, even by nothing
    assert read_kept(tmp_path) == {}


@pytest.mark.parametrize("text", ["{not json", '{"sweep": "s"}', '{"runs": [{"name": "a"}]}', "[1, 2]"])
def test_a_file_that_is_not_a_summary_is_refused_with_its_name(tmp_path: Path, text: str) -> None:
    path = tmp_path / "runs.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=f"{path}: not a gns-bench run summary"):
        read_run_summary(path)
    with pytest.raises(ValueError, match="not a gns-bench run summary"):
        record_runs(path, "s", "smoke", [record("a", 1.0)])
    assert path.read_text() == text  # nothing written over it
