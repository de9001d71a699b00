"""A study report's candidate tables (report/study.py)."""

from __future__ import annotations

from types import SimpleNamespace

from gns_bench import tracking
from gns_bench.report.cells import DIAGNOSTIC_COLUMNS
from gns_bench.report.collect import RunRow
from gns_bench.report.study import diagnostics_table


def _row(metrics: dict[str, float], status: str = "FINISHED") -> RunRow:
    return RunRow(SimpleNamespace(name="r"), tracking.RunRecord("id", "r", status, 0,
                                                                metrics={f"test/{k}": v for k, v in metrics.items()}))


def test_the_diagnostics_table_gives_each_candidate_s_mean_and_its_seeds() -> None:
    """Every diagnostic the domain table shows, per candidate: the mean over finished seeds with each seed's
    value beside it; a diagnostic older runs did not log is "—" (not "— (— / —)"); a candidate with no
    finished run is left out, and with none at all there is no table."""
    held = _row({"gravity_ratio": 1.0, "held_gravity_ratio": 0.9, "steps_before_trip": 394.0})
    other = _row({"gravity_ratio": 1.2, "held_gravity_ratio": 1.1, "steps_before_trip": 200.0})
    lines = diagnostics_table({"held": [held, other], "single": [held], "lost": [_row({}, status="KILLED")]})
    assert lines[0].count(" | ") == len(DIAGNOSTIC_COLUMNS) + 1 and lines[1].count("---") == len(DIAGNOSTIC_COLUMNS) + 2
    cells = {row[0]: row for row in (line.strip("| ").split(" | ") for line in lines[2:])}
    assert set(cells) == {"`held`", "`single`"}
    both = cells["`held`"]
    assert both[1] == "2" and both[2] == "1.1 (1 / 1.2)" and both[3] == "1 (0.9 / 1.1)"
    assert both[4] == "—"  # rollout gravity ratio not logged by either
    assert both[-1] == "297 (394 / 200)"
    assert cells["`single`"][2] == "1"  # one seed: the value alone
    assert diagnostics_table({"lost": [_row({}, status="KILLED")]}) == []
