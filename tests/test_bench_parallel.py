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


def test_the_index_lists_a_gpus_cuda_tests_and_runs_at_once(tmp_path: Path) -> None:
    """What the GPU check leaves beside a machine's benchmark appears on the index, as measured."""
    import json
    import shutil

    from gns_bench.bench.report import write_bench_index

    folder = tmp_path / "some-gpu"
    folder.mkdir()
    shutil.copy(Path(__file__).parents[1] / "reports/bench/amd-epyc-family-25-model-17-avx512bf16/bench.json", folder)
    (folder / "cuda-tests.xml").write_text(
        '<?xml version="1.0"?><testsuites><testsuite tests="5" failures="1" errors="0" skipped="1"/></testsuites>')
    write_parallel_report({"runs": 4, "steps": 300, "hardware_one_at_a_time": "GPU", "hardware_at_once": "GPU",
                           "seconds_one_at_a_time": 45.4, "seconds_at_once": 48.1, "speedup": 45.4 / 48.1}, folder)
    assert json.loads((folder / "parallel.json").read_text())["runs"] == 4
    index = write_bench_index(tmp_path).read_text()
    assert "CUDA tests (`tests/test_cuda.py`): 3 of 5 passed, 1 failed, 1 skipped" in index
    assert "4 runs at once (300 training steps each): 48.1 s, against 45.4 s one after another, a 0.94x" in index


def test_the_gpu_check_refuses_a_machine_without_cuda(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    from gns_bench.bench.device import run_device_checks

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="no CUDA device"):
        run_device_checks(tmp_path)
    assert not any(tmp_path.iterdir())  # nothing written
