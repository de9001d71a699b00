"""The one place that talks to MLflow.

Default tracking store: an SQLite file `mlflow.db` in the working directory; a local SQLite store keeps
its artifacts beside the database in `mlartifacts/<experiment>/`. `MLFLOW_TRACKING_URI` overrides it
(a team server, say). A run that raises is ended FAILED with its error as a tag; Ctrl-C ends it
KILLED: nothing that did not finish looks FINISHED.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import platform
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

DEFAULT_DB = "mlflow.db"
DEFAULT_ARTIFACTS = "mlartifacts"
CURVE_PREFIX = "curve/"  # metrics logged along training (train.eval_every), read back with their history


def tracking_uri() -> str:
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path.cwd() / DEFAULT_DB}"


def use_tracking_uri(uri: str) -> None:
    """Point this process (and the processes it starts) at a tracking store."""
    os.environ["MLFLOW_TRACKING_URI"] = uri


def configure():
    """Import MLflow (lazily: it takes seconds), quieten it, and point it at our store."""
    return _mlflow()


def _mlflow():
    import mlflow

    logging.getLogger("mlflow").setLevel(logging.WARNING)
    logging.getLogger("alembic").setLevel(logging.WARNING)
    mlflow.set_tracking_uri(tracking_uri())
    return mlflow


def git_sha() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        sha = out.stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, timeout=5, cwd=Path(__file__).resolve().parent).stdout.strip()
        return (sha + ("-dirty" if dirty else "")) if sha else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def hardware_description(device: str) -> str:
    """What a number was measured on, for reports: the GPU's name, or the CPU model and thread count."""
    import torch

    from gns_bench.devices import cpu_model

    if device.startswith("cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    threads = torch.get_num_threads()
    return f"{cpu_model()}, {threads} thread{'' if threads == 1 else 's'}"


def with_generation(hardware: str, device: str, generation: str | None) -> str:
    """`hardware` (as `hardware_description` names it) with the CPU's generation beside it on a CPU: one model
    name ("AMD EPYC") covers generations whose bf16 rates differ 2x; a record from before the generation was
    kept says so."""
    if not device.startswith("cpu"):
        return hardware
    return f"{hardware} (CPU {generation or 'generation not recorded'})"


def environment_tags(device: str) -> dict[str, str]:
    """The tags every run carries about where it ran; `cpu` tells apart CPU generations that share a model
    name (devices.cpu_identity)."""
    import torch

    from gns_bench.devices import cpu_identity

    return {"git_sha": git_sha(), "device": device, "torch_version": torch.__version__,
            "python_version": platform.python_version(), "hardware": hardware_description(device),
            "cpu": cpu_identity()}


# MLflow's experiment kind: "custom_model_development" is its "Machine learning" kind (runs, their metrics and
# parameters), not GenAI (traces, evaluations, prompts). MLflow 3's UI reads it (its assistant too); the 3.17 UI
# picks its layout per browser instead (the "GenAI / Model training" switch, or ?workflowType=machine_learning).
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
EXPERIMENT_KIND = "custom_model_development"


def experiment_id(name: str) -> str:
    """The id of experiment `name`, created (tagged as a model-training experiment) if it does not exist yet;
    an existing one without a kind gets the tag too, one that has a kind keeps it."""
    mlflow = _mlflow()
    experiment = mlflow.get_experiment_by_name(name)
    if experiment is not None:
        _ensure_kind(experiment)
        return experiment.experiment_id
    location = None
    uri = tracking_uri()
    if uri.startswith("sqlite:///"):  # a local store: keep its artifacts beside the database file
        location = (Path(uri.removeprefix("sqlite:///")).resolve().parent / DEFAULT_ARTIFACTS / name).as_uri()
    from mlflow.exceptions import MlflowException

    try:
        return mlflow.create_experiment(name, artifact_location=location, tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND})
    except MlflowException:
        # Parallel runs of one sweep (submitit, torchrun) may create it at the same moment: use theirs.
        experiment = mlflow.get_experiment_by_name(name)
        if experiment is None:
            raise
        _ensure_kind(experiment)
        return experiment.experiment_id


def _ensure_kind(experiment: Any) -> None:
    """Tag an active experiment made before gns-bench set its kind (or by other code) as model training. Only a
    UI hint: a store that refuses the tag (permissions) is warned about, not fatal; a deleted experiment is
    left for `start_run` to refuse with MLflow's own error."""
    if experiment.lifecycle_stage != "active" or EXPERIMENT_KIND_TAG in (experiment.tags or {}):
        return
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    try:
        MlflowClient(tracking_uri=tracking_uri()).set_experiment_tag(experiment.experiment_id, EXPERIMENT_KIND_TAG,
                                                                     EXPERIMENT_KIND)
    except MlflowException as exc:
        logging.getLogger(__name__).warning("could not tag experiment %r with %s=%s: %s", experiment.name,
                                            EXPERIMENT_KIND_TAG, EXPERIMENT_KIND, exc)


PARAM_BATCH = 90  # MLflow caps a batch at 100 params


def as_param_strings(params: dict[str, Any]) -> dict[str, str]:
    """How every param is stored: its str(), and "None" for None."""
    return {k: "None" if v is None else str(v) for k, v in params.items()}


class Run:
    """A thin handle over an active MLflow run."""

    def __init__(self, mlflow: Any, run: Any):
        self._mlflow, self.run = mlflow, run

    @property
    def run_id(self) -> str:
        return self.run.info.run_id

    @property
    def artifact_uri(self) -> str:
        return self.run.info.artifact_uri

    @property
    def params(self) -> dict[str, str]:
        """The params logged when the run was started or continued (as strings)."""
        return dict(self.run.data.params)

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        clean = {k: float(v) for k, v in metrics.items() if v is not None}
        if clean:
            self._mlflow.log_metrics(clean, step=step)

    def log_params(self, params: dict[str, Any]) -> None:
        items = list(as_param_strings(params).items())
        for start in range(0, len(items), PARAM_BATCH):
            self._mlflow.log_params(dict(items[start:start + PARAM_BATCH]))

    def set_tags(self, tags: dict[str, Any]) -> None:
        self._mlflow.set_tags({k: str(v) for k, v in tags.items()})

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        self._mlflow.log_artifact(str(path), artifact_path=artifact_path)

    def log_dict(self, data: dict[str, Any], name: str) -> None:
        self._mlflow.log_dict(data, name)

    def delete_tags(self, keys: list[str]) -> None:
        """Remove those of `keys` the run had when it started (a re-evaluation drops what no longer holds)."""
        for key in keys:
            if key in self.run.data.tags:
                self._mlflow.delete_tag(key)

    def delete_artifact(self, path: str) -> bool:
        """Delete one logged artifact; False when the artifact store cannot delete (the caller says so)."""
        from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

        try:
            get_artifact_repository(self.artifact_uri).delete_artifacts(path)
        except (NotImplementedError, FileNotFoundError, OSError):
            return False
        return True


def start_run(experiment: str, run_name: str, *, params: dict[str, Any] | None = None,
              tags: dict[str, Any] | None = None) -> AbstractContextManager[Run]:
    """Start a new run in `experiment`; it ends FINISHED, or FAILED / KILLED with tag `error` if the block raises."""
    mlflow = _mlflow()
    return _tracked(mlflow, mlflow.start_run(experiment_id=experiment_id(experiment), run_name=run_name),
                    params, tags)


def continue_run(run_id: str, *, params: dict[str, Any] | None = None,
                 tags: dict[str, Any] | None = None) -> AbstractContextManager[Run]:
    """Continue an existing run (a resumed training, a re-evaluation); it ends as `start_run`'s do. The stop
    of an earlier attempt (tag `error`) becomes tag `resumed_after`: history, not how this run ends."""
    mlflow = _mlflow()
    active = mlflow.start_run(run_id=run_id)
    earlier = active.data.tags.get("error")
    if earlier is not None:
        mlflow.set_tag("resumed_after", earlier)
        mlflow.delete_tag("error")
    return _tracked(mlflow, active, params, tags)


@contextmanager
def _tracked(mlflow: Any, active: Any, params: dict[str, Any] | None, tags: dict[str, Any] | None) -> Iterator[Run]:
    handle = Run(mlflow, active)
    try:
        if params:
            handle.log_params(params)
        if tags:
            handle.set_tags(tags)
        yield handle
    except KeyboardInterrupt:
        mlflow.set_tag("error", "interrupted (KeyboardInterrupt)")
        mlflow.end_run(status="KILLED")
        raise
    except BaseException as exc:
        mlflow.set_tag("error", f"{type(exc).__name__}: {exc}"[:5000])
        mlflow.end_run(status="FAILED")
        raise
    else:
        mlflow.end_run(status="FINISHED")


# ----------------------------------------------------------------------------------------------
# Reading runs back (reports): plain records, so callers never touch MLflow objects.
# ----------------------------------------------------------------------------------------------

@dataclass
class RunRecord:
    """One MLflow run as the reports need it: ids, status, params, latest metrics and tags."""

    run_id: str
    name: str
    status: str  # FINISHED, FAILED, KILLED, RUNNING
    start_time: int  # ms since the epoch
    params: dict[str, str] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)
    tags: dict[str, str] = field(default_factory=dict)
    curves: dict[str, list[tuple[int, float]]] = field(default_factory=dict)  # metric -> (step, value), if read


_VIEW: dict[tuple[str, str, str | None], list[RunRecord]] | None = None  # `search_runs`' answers in `one_view`


@contextmanager
def one_view() -> Iterator[None]:
    """Within it, a search asked again answers as it did the first time (copies of the same records): a report
    build reads every sweep's runs, at each tier, many times over (the front page alone about 300 searches),
    and each search costs a query of the store. For readers: a run logged within is not seen by a search
    already made. Nested views are one view."""
    global _VIEW
    if _VIEW is not None:
        yield
        return
    _VIEW = {}
    try:
        yield
    finally:
        _VIEW = None


def _copied(record: RunRecord) -> RunRecord:
    return dataclasses.replace(record, params=dict(record.params), metrics=dict(record.metrics),
                               tags=dict(record.tags), curves=dict(record.curves))


def search_runs(filter_string: str = "", experiment: str | None = None) -> list[RunRecord]:
    """The (not deleted) runs matching an MLflow filter string, newest first: those of `experiment`, or of
    every experiment when it is None. An experiment that does not exist has no runs."""
    key = (tracking_uri(), filter_string, experiment)
    if _VIEW is not None and key in _VIEW:
        return [_copied(r) for r in _VIEW[key]]
    mlflow = _mlflow()
    if experiment is not None and mlflow.get_experiment_by_name(experiment) is None:
        records = []
    else:
        where = {"experiment_names": [experiment]} if experiment is not None else {"search_all_experiments": True}
        runs = mlflow.search_runs(**where, filter_string=filter_string, output_format="list",
                                  order_by=["attributes.start_time DESC"])
        records = [RunRecord(r.info.run_id, r.info.run_name or "", r.info.status, int(r.info.start_time or 0),
                             dict(r.data.params), dict(r.data.metrics), dict(r.data.tags)) for r in runs]
    if _VIEW is not None:
        _VIEW[key] = records
        return [_copied(r) for r in records]
    return records


def search_sweep_runs(experiment: str, tier: str | None = None) -> list[RunRecord]:
    """Every (not deleted) run of an experiment, newest first; only those tagged `tier` when given."""
    return search_runs(f"tags.tier = '{tier}'" if tier else "", experiment)


def copy_run(source: RunRecord, experiment: str, run_name: str, *, params: dict[str, Any],
             tags: dict[str, Any]) -> str:
    """A new FINISHED run in `experiment` that stands for `source` without retraining it: `source`'s params
    (with `params` over them), latest metrics, the whole history of its `curve/` metrics (at their training
    steps, so the copy's curves are the source's) and tags (with `tags` over them, and `shared_from` = its run
    id). Its artifacts stay with `source`, where `shared_from` leads. Returns the new run's id; a copy that
    fails half-way is ended FAILED, so it never looks complete."""
    from mlflow.entities import Metric, Param
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=tracking_uri())
    all_tags = {k: v for k, v in source.tags.items() if not k.startswith("mlflow.")}
    all_tags.update({k: str(v) for k, v in tags.items()})
    all_tags["shared_from"] = source.run_id
    run_id = client.create_run(experiment_id(experiment), run_name=run_name, tags=all_tags).info.run_id
    try:
        now = int(time.time() * 1000)
        merged = {**source.params, **as_param_strings(params)}
        metrics = [Metric(k, v, now, 0) for k, v in source.metrics.items() if not k.startswith(CURVE_PREFIX)]
        for key in (k for k in source.metrics if k.startswith(CURVE_PREFIX)):
            metrics += [Metric(key, value, now, step) for step, value in metric_history(source.run_id, key)]
        entities = [Param(k, v) for k, v in merged.items()] + metrics
        for start in range(0, len(entities), PARAM_BATCH):
            chunk = entities[start:start + PARAM_BATCH]
            client.log_batch(run_id, params=[e for e in chunk if isinstance(e, Param)],
                             metrics=[e for e in chunk if isinstance(e, Metric)])
    except BaseException as exc:
        client.set_tag(run_id, "error", f"copying run {source.run_id}: {type(exc).__name__}: {exc}"[:5000])
        client.set_terminated(run_id, status="FAILED")
        raise
    client.set_terminated(run_id, status="FINISHED")
    return run_id


def ui_url(port: int = 5000, experiment: str | None = None, run_id: str | None = None) -> str:
    """Where `gns-bench ui` shows an experiment or a run. MLflow 3.17's UI opens in its GenAI layout unless the
    URL asks for the model-training one (`workflowType=machine_learning`; the experiment kind tag alone does not
    switch it), so every link gns-bench prints asks for it."""
    page = ""
    if experiment is not None or run_id is not None:
        mlflow = _mlflow()
        if run_id is not None:
            page = f"experiments/{mlflow.get_run(run_id).info.experiment_id}/runs/{run_id}"
        else:
            found = mlflow.get_experiment_by_name(experiment)
            page = f"experiments/{found.experiment_id}" if found else ""
    return f"http://127.0.0.1:{port}/#/{page}?workflowType=machine_learning"


def serve_ui(port: int = 5000) -> int:
    """Serve the MLflow UI for this store on 127.0.0.1:`port` until it exits or this process is interrupted
    (Ctrl-C, or SIGTERM through `cli.interrupt_on_signals`); then its whole process group goes down with it:
    `mlflow ui` runs its web server as child processes, which outlive a plain kill of `mlflow ui` itself."""
    process = subprocess.Popen([sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", tracking_uri(),
                                "--host", "127.0.0.1", "--port", str(port)], start_new_session=True)
    try:
        return process.wait()
    finally:
        if process.poll() is None:
            _stop_group(process)


def _stop_group(process: subprocess.Popen, grace_seconds: float = 10.0) -> None:
    """SIGTERM the process group `process` leads, then SIGKILL whatever is left after the grace period."""
    try:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=grace_seconds)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    except ProcessLookupError:
        pass


def metric_history(run_id: str, key: str) -> list[tuple[int, float]]:
    """Every (step, value) a run logged for one metric, by step (a resumed run's repeats: the latest)."""
    from mlflow.tracking import MlflowClient

    history = MlflowClient(tracking_uri=tracking_uri()).get_metric_history(run_id, key)
    latest: dict[int, tuple[int, float]] = {}
    for m in history:
        if m.step not in latest or m.timestamp >= latest[m.step][0]:
            latest[m.step] = (m.timestamp, m.value)
    return [(step, value) for step, (_, value) in sorted(latest.items())]


def get_run(run_id: str) -> RunRecord | None:
    """One run by id; None when it does not exist in this store or was deleted."""
    from mlflow.tracking import MlflowClient

    try:
        run = MlflowClient(tracking_uri=tracking_uri()).get_run(run_id)
    except Exception:  # noqa: BLE001 - a run deleted for good or from another store
        return None
    if run.info.lifecycle_stage != "active":
        return None
    return RunRecord(run.info.run_id, run.info.run_name or "", run.info.status, int(run.info.start_time or 0),
                     dict(run.data.params), dict(run.data.metrics), dict(run.data.tags))


def run_record(run_id: str) -> RunRecord | None:
    """`get_run` with the history of its `curve/` metrics (`CURVE_PREFIX`) read into `curves`."""
    record = get_run(run_id)
    if record is not None:
        record.curves = {key: metric_history(run_id, key) for key in record.metrics if key.startswith(CURVE_PREFIX)}
    return record


def end_abandoned_run(run_id: str, reason: str) -> bool:
    """End a run that a killed process left RUNNING (SIGKILL, a lost machine) as KILLED, with `reason` as its
    tag `error`, so the store shows no run as live that nothing will finish. True when it did; a run that
    ended, or is gone, is left as it is."""
    from mlflow.tracking import MlflowClient

    run = get_run(run_id)
    if run is None or run.status != "RUNNING":
        return False
    client = MlflowClient(tracking_uri=tracking_uri())
    client.set_tag(run_id, "error", reason[:5000])
    client.set_terminated(run_id, status="KILLED")
    return True


def delete_run(run_id: str) -> None:
    """Mark a run deleted (MLflow keeps it restorable until its garbage collection)."""
    from mlflow.tracking import MlflowClient

    MlflowClient(tracking_uri=tracking_uri()).delete_run(run_id)


def download_artifacts(run_id: str, artifact_path: str, dst: str | Path) -> Path | None:
    """Copy one artifact (file or folder) of a run into `dst`; None when the run has no such artifact."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # reports print their own output
    mlflow = _mlflow()
    Path(dst).mkdir(parents=True, exist_ok=True)
    try:
        local = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=artifact_path, dst_path=str(dst),
                                                    tracking_uri=tracking_uri())
    except Exception:  # noqa: BLE001 - MLflow raises several types for a missing artifact
        return None
    return Path(local)
