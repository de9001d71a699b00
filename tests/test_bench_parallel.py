"""`python -m gns_bench.bench.parallel` (what `nox -s device` runs on a GPU): both ways finish every run, the
cores are divided when runs go at once, and the report prints the two times beside their ratio."""

from __future__ import annotations

from pathlib import Path

import pytest

from gns_bench.bench.parallel import measure_parallel, write_parallel_report
from gns_bench.devices import usable_core_ids


def test_parallel_timing_runs_both_ways_and_reports_the_ratio(tmp_path: Path) -> None:
    result = measure_parallel(2, steps=3, device="cpu", root=tmp_path / "scratch")
    assert result["seconds_one_at_a_time"] > 0 and result["seconds_at_once"] > 0
    assert result["speedup"] == pytest.approx(result["seconds_one_at_a_time"] / result["seconds_at_once"])
    threads = int(result["hardware_at_once"].rsplit(", ", 1)[1].split()[0])
    assert threads == max(len(usable_core_ids()) // 2, 1)  # each of the 2 runs on its half of the cores
    text = write_parallel_report(result, tmp_path / "out").read_text()
    assert f"{result['speedup']:.2f}x" in text and (tmp_path / "out" / "parallel.json").is_file()
