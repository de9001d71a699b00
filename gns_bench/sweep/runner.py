"""Run a sweep: ensure each run's dataset, skip what already finished, train and evaluate the rest.

A run is identified by its key: a hash of its resolved config, its domain and its dataset's content
hash. A run whose key has a FINISHED MLflow run in the sweep's experiment is skipped; deleting that
MLflow run makes it run again. A run that fails is recorded FAILED with its error and the sweep goes on;
Ctrl-C marks the run in flight KILLED and stops the sweep, and the next invocation resumes it from its
checkpoint.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from gns_bench import tracking
from gns_bench.config import Config
from gns_bench.data.format import read_metadata
from gns_bench.data.generate import dataset_path, ensure_dataset
from gns_bench.pipeline import RUN_ID_FILE, train_run
from gns_bench.sweep.spec import PlannedRun, SweepSpec


@dataclass
class RunOutcome:
    name: str
    status: str  # FINISHED, SKIPPED, FAILED
    run_id: str = ""
    error: str = ""
    metrics: dict[str, float] | None = None


KEY_VERSION = 2  # 1: every config field in the key (before 2026-11-22)
_MISSING = object()


def run_key(run: PlannedRun, dataset_hash: str) -> str:
    """Only the config values that differ from `Config()`'s enter the key, so adding a config field with a
    default leaves every existing run's key (and its FINISHED status) as it was. Changing an existing
    default changes what the keys that omit it mean: bump `KEY_VERSION` with it."""
    defaults = Config().to_dict()
    config = {section: {k: v for k, v in values.items() if defaults.get(section, {}).get(k, _MISSING) != v}
              for section, values in run.config.to_dict().items()}
    payload = {"config": config, "domain": run.domain, "dataset_hash": dataset_hash, "version": KEY_VERSION}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:32]


def finished_keys(experiment: str) -> dict[str, str]:
    """run_key -> run id of the FINISHED (not deleted) runs of an experiment."""
    import mlflow

    tracking.configure()
    if mlflow.get_experiment_by_name(experiment) is None:
        return {}
    runs = mlflow.search_runs(experiment_names=[experiment], filter_string="attributes.status = 'FINISHED'",
                              output_format="list")
    return {r.data.tags["run_key"]: r.info.run_id for r in runs if "run_key" in r.data.tags}


def run_dir(runs_root: Path, run: PlannedRun) -> Path:
    return runs_root / run.sweep / run.tier / run.name


def _resumable(out_dir: Path) -> bool:
    """An earlier attempt left a checkpoint and an MLflow run that still exists (KILLED, FAILED, RUNNING)."""
    from mlflow.tracking import MlflowClient

    id_file = out_dir / RUN_ID_FILE
    if not (id_file.exists() and (out_dir / "checkpoint.pt").exists()):
        return False
    try:
        run = MlflowClient(tracking_uri=tracking.tracking_uri()).get_run(id_file.read_text().strip())
    except Exception:  # noqa: BLE001 - a run deleted for good or from another store
        return False
    return run.info.lifecycle_stage == "active" and run.info.status != "FINISHED"


def execute_run(run: PlannedRun, data_root: Path, runs_root: Path, tracking_uri: str | None = None,
                progress: bool = True) -> RunOutcome:
    """Train and evaluate one planned run (its dataset must exist). Picklable for submitit."""
    if tracking_uri:
        tracking.use_tracking_uri(tracking_uri)
    dataset = dataset_path(run.domain, run.dataset_tier, run.dataset_seed, data_root)
    key = run_key(run, read_metadata(dataset).content_hash or "")
    out_dir = run_dir(runs_root, run)
    resume = _resumable(out_dir)
    if not resume and out_dir.exists():
        shutil.rmtree(out_dir)  # a finished run whose MLflow record was deleted, or a foreign leftover
    try:
        summary = train_run(
            run.config, dataset, out_dir, experiment=f"sweep:{run.sweep}", run_name=run.name, resume=resume,
            progress=progress,
            extra_params={"sweep.name": run.sweep, "sweep.tier": run.tier, "sweep.domain": run.domain,
                          "sweep.dataset_tier": run.dataset_tier},
            extra_tags={"run_key": key, "sweep": run.sweep, "tier": run.tier, "axes": ",".join(run.axes),
                        "kind": "sweep"})
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - the run is already recorded FAILED in MLflow; the sweep goes on
        run_id = (out_dir / RUN_ID_FILE).read_text().strip() if (out_dir / RUN_ID_FILE).exists() else ""
        return RunOutcome(run.name, "FAILED", run_id, f"{type(exc).__name__}: {exc}")
    return RunOutcome(run.name, "FINISHED", summary.run_id, metrics=summary.metrics)


def prepare(sweep: SweepSpec, tier: str, data_root: Path, *, generate: bool = True, progress: bool = True
            ) -> tuple[list[PlannedRun], dict[str, str]]:
    """Plan the runs and ensure their datasets; returns the runs and each run's status before running."""
    runs = sweep.plan(tier)
    done = finished_keys(sweep.experiment)
    status = {}
    for run in runs:
        path = dataset_path(run.domain, run.dataset_tier, run.dataset_seed, data_root)
        if generate:
            ensure_dataset(run.domain, run.dataset_tier, run.dataset_seed, data_root, progress=progress)
        if not (path / "metadata.json").exists():
            status[run.name] = "dataset missing"
            continue
        key = run_key(run, read_metadata(path).content_hash or "")
        status[run.name] = "finished" if key in done else "to run"
    return runs, status


def format_plan(sweep: SweepSpec, tier: str, runs: list[PlannedRun], status: dict[str, str]) -> str:
    header = ["#", "run", *[axis.split(".")[1] for axis in sweep.axes], "seed", "dataset", "status"]
    rows = [[str(i), r.name, *[str(r.axes[a]) for a in sweep.axes], str(r.seed),
             f"{r.domain}-{r.dataset_tier}-s{r.dataset_seed}", status.get(r.name, "")] for i, r in enumerate(runs)]
    widths = [max(len(row[c]) for row in [header, *rows]) for c in range(len(header))]
    lines = [f"sweep {sweep.name} (tier {tier}, MLflow experiment '{sweep.experiment}'): {len(runs)} runs"]
    for row in [header, *rows]:
        lines.append("  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)))
    return "\n".join(lines)


def run_sweep(sweep: SweepSpec, tier: str, *, data_root: Path = Path("data"), runs_root: Path = Path("runs"),
              launcher: str = "local", cluster: str | None = None, progress: bool = True,
              echo: Callable[[str], None] = print) -> list[RunOutcome]:
    runs, status = prepare(sweep, tier, data_root, progress=progress)
    pending = [r for r in runs if status[r.name] == "to run"]
    outcomes = [RunOutcome(r.name, "SKIPPED") for r in runs if status[r.name] == "finished"]
    echo(f"sweep {sweep.name} (tier {tier}): {len(runs)} runs, {len(outcomes)} already finished, "
         f"{len(pending)} to run")
    if launcher == "local":
        for index, run in enumerate(pending, 1):
            echo(f"[{index}/{len(pending)}] {run.name}")
            outcome = execute_run(run, data_root, runs_root, progress=progress)
            if outcome.status == "FAILED":
                echo(f"  FAILED: {outcome.error}")
            outcomes.append(outcome)
    elif launcher == "submitit":
        from gns_bench.sweep.launchers import submit

        outcomes += submit(pending, data_root, runs_root / sweep.name / tier / "submitit", runs_root, cluster)
    else:
        raise ValueError(f"unknown launcher {launcher!r}; expected 'local' or 'submitit'")
    return outcomes
