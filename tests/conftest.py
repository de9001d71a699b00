"""Shared fixtures: a tiny dataset made once per session, and an MLflow store per test session."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from gns_bench.data.tiny import generate_tiny


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_tiny(tmp_path_factory.mktemp("data") / "tiny", "smoke", seed=0)


@pytest.fixture(scope="session", autouse=True)
def isolated_mlflow(tmp_path_factory: pytest.TempPathFactory):
    """Every test session logs into its own SQLite store, never the user's."""
    db = tmp_path_factory.mktemp("mlflow") / "mlflow.db"
    previous = os.environ.get("MLFLOW_TRACKING_URI")
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{db}"
    yield db
    if previous is None:
        os.environ.pop("MLFLOW_TRACKING_URI", None)
    else:
        os.environ["MLFLOW_TRACKING_URI"] = previous


@pytest.fixture(scope="session", autouse=True)
def isolated_autotune_cache(tmp_path_factory: pytest.TempPathFactory):
    """Measured speed choices (gns_bench/autotune.py) go to a cache of this session's, never the user's."""
    previous = os.environ.get("GNS_BENCH_CACHE")
    os.environ["GNS_BENCH_CACHE"] = str(tmp_path_factory.mktemp("autotune"))
    yield
    if previous is None:
        os.environ.pop("GNS_BENCH_CACHE", None)
    else:
        os.environ["GNS_BENCH_CACHE"] = previous


REPORTS = Path(__file__).resolve().parent.parent / "reports"


@pytest.fixture(scope="session", autouse=True)
def committed_reports_untouched():
    """No test writes into the repository's reports/ (the runner records runs under `--reports-root`,
    `reports` by default): a test that forgets to point it elsewhere fails the session here."""
    def files() -> dict[Path, int]:
        return {p: p.stat().st_mtime_ns for p in REPORTS.rglob("*") if p.is_file()}

    before = files()
    yield
    after = files()
    changed = sorted(str(p.relative_to(REPORTS)) for p in after if before.get(p) != after[p])
    assert not changed, f"tests wrote into reports/: {changed[:10]}"
