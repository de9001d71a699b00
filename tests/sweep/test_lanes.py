"""Lanes (`sweep/launchers.Lanes`): a stop reaches the jobs in the lanes, and no queued job begins after it."""
from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from gns_bench.sweep.launchers import Lanes

SLEEP_S = 30  # each job's length: far longer than a stop may take


def _job(marker: Path) -> tuple:
    """A job that says it began, then runs SLEEP_S seconds (a child process, killed when the job is
    interrupted: `subprocess.run` kills its child on any exception)."""
    return subprocess.run, ["sh", "-c", f"touch {marker}; sleep {SLEEP_S}"]


def test_leaving_the_lanes_by_an_interrupt_stops_their_jobs_and_starts_no_queued_one(tmp_path: Path) -> None:
    markers = [tmp_path / f"began-{i}" for i in range(3)]
    with pytest.raises(KeyboardInterrupt):
        with Lanes(2) as lanes:
            futures = [lanes.submit(*_job(marker)) for marker in markers]  # the third waits for a lane
            deadline = time.monotonic() + 120
            while not (markers[0].exists() and markers[1].exists()):
                assert time.monotonic() < deadline, "the lanes never began their jobs"
                time.sleep(0.1)
            stopped = time.monotonic()
            raise KeyboardInterrupt  # what a SIGTERM to this process alone becomes (cli.interrupt_on_signals)
    assert time.monotonic() - stopped < SLEEP_S / 2  # the jobs were interrupted, not waited for
    assert not markers[2].exists()  # the job a worker held queued never began
    assert all(future.done() for future in futures)
    assert all(isinstance(future.exception(), KeyboardInterrupt) for future in futures[:2])
    assert futures[2].cancelled() or "not started" in str(futures[2].exception())
