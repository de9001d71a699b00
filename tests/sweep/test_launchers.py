"""The submitit launcher runs the job it is given on every run and reports jobs that died."""

from __future__ import annotations

from pathlib import Path

from gns_bench.sweep.launchers import submit


def double_or_fail(value: int) -> int:
    if value < 0:
        raise RuntimeError("negative on purpose")
    return 2 * value


def test_submit_returns_each_result_or_why_its_job_died(tmp_path: Path) -> None:
    results = submit(double_or_fail, [1, -1, 3], tmp_path, cluster="local")  # local processes, as on one machine
    assert results[0] == 2 and results[2] == 6
    assert isinstance(results[1], str) and "negative on purpose" in results[1]
    assert submit(double_or_fail, [], tmp_path) == []
