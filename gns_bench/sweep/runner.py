"""Run a sweep: ensure each run's dataset, skip what already finished, train and evaluate the rest.

A run is identified by its key: a hash of its resolved config, its domain and its dataset's content
hash. A run whose key has a FINISHED MLflow run in the sweep's experiment is skipped; deleting that
MLflow run makes it run again. A run whose key another sweep already trained (every ablation's default
point is the domain sweep's run) is shared, not retrained: the sweep's experiment gets a copy of that run's
params and metrics, tagged `shared_from` with its run id (where its artifacts stay). A stress sweep's run
whose model another sweep trained (the same config but for [stress]) stress-tests that run's checkpoint
instead of training it again. A run that fails is
recorded FAILED with its error and the sweep goes on; Ctrl-C marks the run in flight KILLED and stops the
sweep, and the next invocation resumes it from its checkpoint.

The runner writes each run into its sweep's run summary (`reports/<sweep>/<tier>/runs.json`,
`sweep/summaries.py`) as the run finishes. The committed summaries count as finished runs, so a
campaign resumed on a machine whose MLflow store is gone does not train again what the repository reports: a
run whose key a summary of its sweep holds is finished, one whose key a summary of another sweep holds is
shared from that record (params and metrics; its artifacts are gone), and a run its sweep's summary holds is
known finished without generating its datasets again when the key recomputed from the datasets that summary
names (their content hashes) is the summary's key. A stress run whose model only a summary holds trains it
again: its checkpoint is not there to test.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fnmatch
import hashlib
import json
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from gns_bench import autotune, tracking
from gns_bench.config import Config, StressConfig, resolve_for_dataset
from gns_bench.data.format import read_metadata
from gns_bench.datasets import dataset_complete, dataset_path, ensure_dataset, resolve_for_domain
from gns_bench.devices import resolve_device
from gns_bench.pipeline import RUN_ID_FILE, reevaluate_run, stress_trained, train_run
from gns_bench.sweep import cpu_kinds
from gns_bench.sweep.spec import PlannedRun, SweepSpec
from gns_bench.sweep.summaries import RESTORED_FROM, record_runs, summarised_runs, summary_path
from gns_bench.train.checkpoints import CHECKPOINT_NAME


@dataclass
class RunOutcome:
    name: str
    status: str  # FINISHED, SKIPPED, SHARED, REEVALUATED, FAILED, WAITING (for another kind of machine, or the
    # checkpoint a branch starts from)
    run_id: str = ""
    error: str = ""
    metrics: dict[str, float] | None = None


# 1: every config field in the key (before 2026-11-22). 2: only fields that differ from Config()'s.
# 3: configs resolved against their dataset before keying, and the release's defaults.
KEY_VERSION = 3
KEYED_SECTIONS = ("model", "train", "eval", "stress")  # the config's sections at KEY_VERSION 3: always in the key
_MISSING = object()


def run_key(config: Config, domain: str, dataset_hash: str, eval_dataset_hash: str | None = None) -> str:
    """Only the config values that differ from `Config()`'s enter the key, so adding a config field with a
    default leaves every existing run's key (and its FINISHED status) as it was. Changing an existing
    default changes what the keys that omit it mean: bump `KEY_VERSION` with it. `config` is resolved
    against the dataset (`dataset_run_key`), so the radius ablation's R = 0.015 point is the GOOP run."""
    defaults = Config().to_dict()
    config_values = {section: {k: v for k, v in values.items() if defaults.get(section, {}).get(k, _MISSING) != v}
                     for section, values in config.to_dict().items()}
    # A section added since (e.g. [cconv], [dpi]) enters only when it holds a non-default value, as a field does.
    config_values = {section: values for section, values in config_values.items()
                     if values or section in KEYED_SECTIONS}
    payload = {"config": config_values, "domain": domain, "dataset_hash": dataset_hash, "version": KEY_VERSION}
    if eval_dataset_hash is not None:  # evaluated on another dataset than it trains on (a study's candidate)
        payload["eval_dataset_hash"] = eval_dataset_hash
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:32]


def dataset_run_key(run: PlannedRun, data_root: Path) -> str:
    """`run_key` of a run on its datasets under `data_root`: its config resolved against the one it trains on,
    the content hashes of that one (and of the one it is evaluated on, when that is another)."""
    metadata = read_metadata(training_data(run, data_root))
    config = resolve_for_dataset(run.config, metadata.default_connectivity_radius)
    evaluated = read_metadata(evaluation_data(run, data_root)).content_hash if run.evaluated_elsewhere else None
    return run_key(config, run.domain, metadata.content_hash or "", evaluated)


def summary_key(run: PlannedRun, record: tracking.RunRecord) -> str | None:
    """The key `run` has on the datasets that `record` (a run summary's) trained and was evaluated on, by their
    content hashes in its tags: the record's own `run_key` exactly when it is this run on those datasets, so it
    is known finished with no dataset at hand. None when the record names no dataset hash."""
    dataset_hash = record.tags.get("dataset_hash")
    evaluated = record.tags.get("eval_dataset_hash") if run.evaluated_elsewhere else None
    if not dataset_hash or (run.evaluated_elsewhere and not evaluated):
        return None
    config = resolve_for_domain(run.config, run.training_domain)
    return run_key(config, run.domain, dataset_hash, evaluated)


def training_data(run: PlannedRun, data_root: Path) -> Path:
    return dataset_path(run.training_domain, run.dataset_tier, run.dataset_seed, data_root)


def evaluation_data(run: PlannedRun, data_root: Path) -> Path:
    """The dataset whose split the run is evaluated on: its training data unless the sweep names another."""
    return dataset_path(run.domain, run.evaluated_on, run.dataset_seed, data_root)


def finished_keys(experiment: str) -> dict[str, tracking.RunRecord]:
    """run_key -> the newest FINISHED (not deleted) run of an experiment with that key."""
    finished: dict[str, tracking.RunRecord] = {}
    for record in tracking.search_runs("attributes.status = 'FINISHED'", experiment):  # newest first
        if "run_key" in record.tags:
            finished.setdefault(record.tags["run_key"], record)
    return finished


def trained_keys(domain: str, summarised: Sequence[tracking.RunRecord] = ()) -> dict[str, tracking.RunRecord]:
    """run_key -> the newest FINISHED sweep run of any experiment that trained it (copies excluded), among
    the runs on `domain` (the key holds the domain, so no other run can match); then, for keys MLflow lacks,
    the `summarised` records (`summaries.summarised_runs`) that trained one."""
    runs = tracking.search_runs("attributes.status = 'FINISHED' and tags.kind = 'sweep' and "
                                f"params.`sweep.domain` = '{domain}'")
    trained: dict[str, tracking.RunRecord] = {}
    for record in [*runs, *(r for r in summarised if r.params.get("sweep.domain") == domain
                             and r.tags.get("kind") == "sweep")]:  # newest first, MLflow's before the summaries'
        if "run_key" in record.tags and "shared_from" not in record.tags:
            trained.setdefault(record.tags["run_key"], record)
    return trained


def _sweep_params(run: PlannedRun) -> dict[str, str]:
    return {"sweep.name": run.sweep, "sweep.tier": run.tier, "sweep.domain": run.domain,
            "sweep.dataset_tier": run.dataset_tier, "sweep.dataset_domain": run.training_domain,
            "sweep.eval_dataset_tier": run.evaluated_on}


def _sweep_tags(run: PlannedRun, key: str) -> dict[str, str]:
    return {"run_key": key, "sweep": run.sweep, "tier": run.tier, "axes": ",".join(run.axes), "kind": "sweep"}


def run_dir(runs_root: Path, run: PlannedRun) -> Path:
    return runs_root / run.sweep / run.tier / run.name


@contextlib.contextmanager
def stderr_into(path: Path) -> Iterator[None]:
    """This process's stderr (progress bars, warnings) appended to `path`, line by line, while the block runs."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", buffering=1) as log, contextlib.redirect_stderr(log):
        yield


def _resumable(out_dir: Path, key: str) -> bool:
    """An earlier attempt at this run left a checkpoint and an MLflow run that still exists (KILLED, FAILED,
    RUNNING) under the same key. A different key means the plan changed under it (a tier's budget, a new
    dataset): that attempt is another run, and this one starts afresh."""
    id_file = out_dir / RUN_ID_FILE
    if not (id_file.exists() and (out_dir / "checkpoint.pt").exists()):
        return False
    run = tracking.get_run(id_file.read_text().strip())
    return run is not None and run.status != "FINISHED" and run.tags.get("run_key") == key


def set_aside(out_dir: Path) -> Path:
    """Move a run directory this plan cannot resume out of the way, to `<name>.set-aside-<n>` beside it, never
    deleting it: its checkpoint may be the only copy of hours of training (a plan whose key changed under it).
    Its MLflow run, if a killed process left it RUNNING, ends KILLED with a tag naming the new folder."""
    index = 1
    while (target := out_dir.with_name(f"{out_dir.name}.set-aside-{index}")).exists():
        index += 1
    out_dir.rename(target)
    print(f"{out_dir}: not resumable under this plan; moved to {target.name}", flush=True)
    if (id_file := target / RUN_ID_FILE).exists():
        tracking.end_abandoned_run(id_file.read_text().strip(),
                                   f"abandoned: its process ended without a checkpoint or under another plan; "
                                   f"folder set aside to {target}")
    return target


def as_outcome(run: PlannedRun, result: RunOutcome | str) -> RunOutcome:
    """A dispatched run's outcome: its own, or FAILED with the message of a process that died outside it."""
    return result if isinstance(result, RunOutcome) else RunOutcome(run.name, "FAILED", error=str(result))


PROGRESS_LOG = "progress.log"  # a run's progress bars when it runs in a lane of its own (`progress_log`)


def execute_run(run: PlannedRun, data_root: Path, runs_root: Path, tracking_uri: str | None = None,
                progress: bool = True, progress_log: bool = False) -> RunOutcome:
    """Train and evaluate one planned run (its dataset must exist). Picklable for submitit. `progress_log`:
    the run's progress (steps/s, ETA; its warnings too) goes to `PROGRESS_LOG` in its run directory instead of
    this process's stderr, for a run that shares the terminal with others (`tail -f` it)."""
    if tracking_uri:
        tracking.use_tracking_uri(tracking_uri)
    dataset = training_data(run, data_root)
    key = dataset_run_key(run, data_root)
    out_dir = run_dir(runs_root, run)
    trunk = branch_checkpoint(run.config, runs_root)
    config = run.config if trunk is None else dataclasses.replace(
        run.config, train=dataclasses.replace(run.config.train, init_from=str(trunk)))
    resume = _resumable(out_dir, key)
    if not resume and out_dir.exists():
        set_aside(out_dir)  # another plan's attempt (its key differs), or a run whose MLflow record is gone
    try:
        with stderr_into(out_dir / PROGRESS_LOG) if progress_log else contextlib.nullcontext():
            summary = train_run(
                config, dataset, out_dir, experiment=f"sweep:{run.sweep}", run_name=run.name, resume=resume,
                eval_dataset_dir=evaluation_data(run, data_root) if run.evaluated_elsewhere else None,
                progress=progress or progress_log, extra_params=_sweep_params(run), extra_tags=_sweep_tags(run, key))
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - the run is already recorded FAILED in MLflow; the sweep goes on
        run_id = (out_dir / RUN_ID_FILE).read_text().strip() if (out_dir / RUN_ID_FILE).exists() else ""
        return RunOutcome(run.name, "FAILED", run_id, f"{type(exc).__name__}: {exc}")
    return RunOutcome(run.name, "FINISHED", summary.run_id, metrics=summary.metrics)


def reevaluate(sweep: SweepSpec, runs: list[PlannedRun], data_root: Path, runs_root: Path, *,
               reason: str, progress: bool = True, echo: Callable[[str], None] = print) -> list[RunOutcome]:
    """Evaluate this sweep's finished runs again with today's evaluation, each into its own MLflow run
    (`pipeline.reevaluate_run`); the runs it holds as copies of other sweeps' runs are copied afresh from
    their sources, so re-evaluate the sweep that trained them first. Training is untouched."""
    records = finished_keys(sweep.experiment)
    outcomes = []
    for run in runs:
        key = dataset_run_key(run, data_root)
        record = records.get(key)
        if record is None:
            continue
        if record.tags.get("stress_tested") == "here":  # pipeline.stress_trained's run
            echo(f"  {run.name}: stress tests of {record.tags.get('shared_from_run', '?')}'s model, left as they "
                 f"were (delete run {record.run_id} to test again)")
            continue
        if "shared_from" in record.tags:
            source = trained_keys(run.domain).get(key)
            if source is None:
                echo(f"  {run.name}: its source run {record.tags['shared_from']} is gone; copy left as it was")
                continue
            outcomes.append(share_run(run, key, source))  # the new copy first: a failed copy ends FAILED
            tracking.delete_run(record.run_id)
            echo(f"  {run.name}: copied afresh from {source.tags.get('sweep', '?')}/{source.name} ({source.run_id})")
            continue
        echo(f"  {run.name}: evaluating {record.run_id} again")
        summary = reevaluate_run(record.run_id, evaluation_data(run, data_root), run_dir(runs_root, run),
                                 run.config.eval, reason=reason, progress=progress)
        outcomes.append(RunOutcome(run.name, "REEVALUATED", summary.run_id, metrics=summary.metrics))
    return outcomes


def share_run(run: PlannedRun, key: str, source: tracking.RunRecord) -> RunOutcome:
    """Record `source` (trained by another sweep with the same key) as this planned run, without training."""
    run_id = tracking.copy_run(source, f"sweep:{run.sweep}", run.name, params=_sweep_params(run),
                               tags={**_sweep_tags(run, key), "shared_from_run": f"{source.tags.get('sweep', '?')}"
                                                                                 f"/{source.name}"})
    return RunOutcome(run.name, "SHARED", run_id, metrics=source.metrics)


def stress_trained_run(run: PlannedRun, key: str, source: tracking.RunRecord, data_root: Path, runs_root: Path,
                       progress: bool = True) -> RunOutcome:
    """`run`'s stress tests on the checkpoint of `source`, which another sweep trained with `run`'s config but
    for its [stress] section: a run of its own holding `source`'s metrics and the stress results
    (`pipeline.stress_trained`). A failure is recorded FAILED, and the sweep goes on."""
    out_dir = run_dir(runs_root, run)
    try:
        summary = stress_trained(
            source, run.config.stress, training_data(run, data_root), out_dir, experiment=f"sweep:{run.sweep}",
            run_name=run.name, extra_params=_sweep_params(run),
            extra_tags={**_sweep_tags(run, key), "shared_from_run": f"{source.tags.get('sweep', '?')}/{source.name}"},
            progress=progress)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - recorded FAILED in MLflow; the sweep goes on
        return RunOutcome(run.name, "FAILED", error=f"{type(exc).__name__}: {exc}")
    return RunOutcome(run.name, "FINISHED", summary.run_id, metrics=summary.metrics)


RECORDED = ("FINISHED", "SHARED", "REEVALUATED")  # the outcomes that leave a finished MLflow run to summarise


def summarise(sweep: SweepSpec, tier: str, reports_root: Path, run_ids: Iterable[str]) -> list[str]:
    """Put the finished MLflow runs `run_ids` (params, final metrics, tags, curves) into the sweep's run summary
    under `reports_root` (`summaries.record_runs`); returns the run names written."""
    records = [r for r in (tracking.run_record(run_id) for run_id in run_ids if run_id) if r is not None]
    return record_runs(summary_path(reports_root, sweep.name, tier), sweep.name, tier, records)


def summarise_finished(sweep: SweepSpec, tier: str, reports_root: Path, names: Iterable[str]) -> list[str]:
    """The newest FINISHED MLflow run of each of `names` (the run a report shows) into the sweep's summary:
    runs finished before the runner kept summaries, or in another process, are recorded too."""
    wanted, newest = set(names), {}
    for record in tracking.search_sweep_runs(sweep.experiment, tier):  # newest first
        if record.status == "FINISHED" and record.name in wanted:
            newest.setdefault(record.name, record.run_id)
    return summarise(sweep, tier, reports_root, newest.values())


def select_runs(sweep: SweepSpec, runs: list[PlannedRun], only: Sequence[str]) -> list[PlannedRun]:
    """The runs whose names match any of the `only` shell patterns (all runs when there are none)."""
    if not only:
        return runs
    chosen = [r for r in runs if any(fnmatch.fnmatchcase(r.name, pattern) for pattern in only)]
    if not chosen:
        raise ValueError(f"sweep {sweep.name}: no run matches --only {' '.join(only)}; its runs are "
                         f"{', '.join(r.name for r in runs)}")
    return chosen


FINISHED = "finished"
SUMMARISED = "finished (committed summary)"  # a run the MLflow store lacks and its sweep's runs.json holds


def prepare(sweep: SweepSpec, tier: str, data_root: Path, *, generate: bool = True, progress: bool = True,
            share: bool = True, only: Sequence[str] = (), reports_root: Path | None = None, any_kind: bool = False,
            runs_root: Path | None = None
            ) -> tuple[list[PlannedRun], dict[str, str], dict[str, tuple[str, tracking.RunRecord]]]:
    """Plan the runs (those matching `only`, if given) and ensure their datasets. Returns the runs, each
    run's status before running (FINISHED, SUMMARISED, "to run", "shared with <sweep>/<run>", "dataset
    missing", "waits for a machine ..."), and the shared ones' (key, trained run) by run name:
    those another sweep trained with the same key (none when `share` is off). `reports_root`: where the
    committed run summaries are read (none: MLflow's runs only). A run to train waits for another kind of
    machine where `sweep/cpu_kinds.py` holds it there, unless `any_kind`: any of a sweep whose runs are compared,
    one that would resume from a checkpoint under `runs_root` (when given) begun on another kind, and one set to
    train in bf16 on a machine with no bf16 unit."""
    runs = select_runs(sweep, sweep.plan(tier), only)
    summarised = summarised_runs(reports_root) if reports_root is not None else []
    saved = {r.name: r for r in summarised if r.tags.get("sweep") == sweep.name and r.tags.get("tier") == tier}
    done = {r.tags["run_key"]: r for r in saved.values() if "run_key" in r.tags} | finished_keys(sweep.experiment)
    trained: dict[str, tracking.RunRecord] = {}
    for domain in {r.domain for r in runs} if share else ():
        trained.update(trained_keys(domain, summarised))
    status: dict[str, str] = {}
    shared: dict[str, tuple[str, tracking.RunRecord]] = {}
    for run in runs:
        datasets = dict.fromkeys([(run.training_domain, run.dataset_tier), (run.domain, run.evaluated_on)])
        record = saved.get(run.name)
        if (not _datasets_made(datasets, run.dataset_seed, data_root) and record is not None
                and summary_key(run, record) == record.tags.get("run_key")):
            status[run.name] = SUMMARISED  # its datasets are not made again only to say so
            continue
        if generate:  # the training data, then the evaluation's
            for domain, dataset_tier in datasets:
                ensure_dataset(domain, dataset_tier, run.dataset_seed, data_root, progress=progress)
        if not _datasets_made(datasets, run.dataset_seed, data_root):
            status[run.name] = "dataset missing"
            continue
        key = dataset_run_key(run, data_root)
        if key in done:
            status[run.name] = FINISHED if RESTORED_FROM not in done[key].tags else SUMMARISED
        elif key in trained:
            source = trained[key]
            status[run.name] = f"shared with {source.tags.get('sweep', '?')}/{source.name}"
            shared[run.name] = (key, source)
        elif ((unstressed := unstressed_key(run, data_root)) in trained  # another sweep trained this model
              and RESTORED_FROM not in trained[unstressed].tags):  # and its checkpoint is here:
            source = trained[unstressed]  # stress-test it
            status[run.name] = f"{STRESSED} {source.tags.get('sweep', '?')}/{source.name}"
            shared[run.name] = (key, source)
        else:
            status[run.name] = "to run"
    if not any_kind:
        _hold_to_kinds(sweep, tier, runs, status, saved, [source for _, source in shared.values()], data_root,
                       runs_root)
    if runs_root is not None:
        for run in runs:
            trunk = branch_checkpoint(run.config, runs_root)
            if status[run.name] == "to run" and trunk is not None and not trunk_ready(trunk):
                status[run.name] = f"{WAITS_FOR_TRUNK} {trunk}"
    return runs, status, shared


WAITS_FOR_TRUNK = "waits for the checkpoint it starts from:"


def trunk_ready(trunk: Path) -> bool:
    """Whether a branch may start from `trunk`: the file is there and final. A kept checkpoint-<step>.pt is
    final once written; a run's own checkpoint.pt only once that run has finished (while it trains, or after
    it stopped part-way, it holds whatever step the run reached)."""
    if not trunk.is_file():
        return False
    id_file = trunk.parent / RUN_ID_FILE
    if trunk.name != CHECKPOINT_NAME or not id_file.exists():
        return True
    record = tracking.get_run(id_file.read_text().strip())
    return record is None or record.status == "FINISHED"  # no record here: no run of this store writes it
RUNS_PREFIX = "runs:"  # train.init_from = "runs:<sweep>/<tier>/<run>/checkpoint-<step>.pt", under the runs root


def branch_checkpoint(config: Config, runs_root: Path) -> Path | None:
    """The checkpoint a run starts from (`train.init_from`), a `runs:` path taken under `runs_root` (so that a
    sweep file names another sweep's kept checkpoint the same way on every machine, and its key with it), with
    `{seed}` replaced by the run's seed (each seed branches from its own trunk); None for a run that starts
    afresh."""
    source = config.train.init_from.replace("{seed}", str(config.train.seed))
    if not source:
        return None
    return runs_root / source.removeprefix(RUNS_PREFIX) if source.startswith(RUNS_PREFIX) else Path(source)


def _hold_to_kinds(sweep: SweepSpec, tier: str, runs: list[PlannedRun], status: dict[str, str],
                   saved: dict[str, tracking.RunRecord], sources: list[tracking.RunRecord], data_root: Path,
                   runs_root: Path | None) -> None:
    """Set the status of each run to train that `sweep/cpu_kinds.py` holds to another kind of machine: one that
    would resume from a checkpoint begun there, or any of a sweep whose runs are compared with each other, once
    most of its runs that trained did so on another kind (`sources`: the runs other sweeps trained that this
    one shares, an ablation's default arm, count where they trained); and, above the smoke tier, one set to train
    in bf16 on a machine with no bf16 unit."""
    to_run = [run for run in runs if status[run.name] == "to run"]
    if not to_run:
        return
    sweep_kind = ""
    if sweep.kind in cpu_kinds.COMPARED:
        attempts = tracking.search_sweep_runs(sweep.experiment, tier)  # newest first
        trained = [r for r in attempts if r.status == "FINISHED" or r.metrics]  # attempts that got to train
        known = {r.name for r in attempts}
        trained += [r for r in saved.values() if r.name not in known]  # the committed summaries' runs MLflow lacks
        trained += sources
        sweep_kind = cpu_kinds.held_kind(cpu_kinds.kind_of(r.tags) for r in sorted(trained, key=lambda r: r.start_time))
    here: dict[str, str] = {}
    for run in to_run:
        device = run.config.train.device
        if device not in here:
            here[device] = cpu_kinds.kind_here(resolve_device(device))
        out_dir = run_dir(runs_root, run) if runs_root is not None else None
        began = ""
        if out_dir is not None and _resumable(out_dir, dataset_run_key(run, data_root)):
            attempt = tracking.get_run((out_dir / RUN_ID_FILE).read_text().strip())
            began = cpu_kinds.kind_of(attempt.tags) if attempt is not None else ""
        if began and began != here[device]:
            status[run.name] = cpu_kinds.waiting_status(began, "it began training there")
        elif sweep_kind and sweep_kind != here[device]:
            status[run.name] = cpu_kinds.waiting_status(sweep_kind, "its sweep's compared runs trained there")
        elif (tier != "smoke"  # seconds a run: a slow bf16 costs seconds
              and run.config.train.precision == "bf16" and not (rates := _matmul_rates(device)).bf16_pays):
            status[run.name] = cpu_kinds.waiting_for_bf16(rates.describe())


def changed_data(sweep: SweepSpec, tier: str, runs: list[PlannedRun], status: dict[str, str], data_root: Path,
                 reports_root: Path | None) -> list[str]:
    """A line for each run to train whose namesake in the committed run summary trained on other data: a dataset
    made again on another machine whose solver's floats came out different, or changed. Its key names the data's
    content hash, so it is another run and trains again; the line says so before it does."""
    if reports_root is None:
        return []
    saved = {r.name: r for r in summarised_runs(reports_root)
             if r.tags.get("sweep") == sweep.name and r.tags.get("tier") == tier}
    lines = []
    for run in runs:
        record = saved.get(run.name)
        if status[run.name] != "to run" or record is None or not record.tags.get("dataset_hash"):
            continue
        path = training_data(run, data_root)
        now = read_metadata(path).content_hash or ""
        if now and now != record.tags["dataset_hash"]:
            lines.append(f"  {run.name}: trains again: the committed run summary's run trained on data hashed "
                         f"{record.tags['dataset_hash'][:12]}, and {path} now hashes {now[:12]} (made again on "
                         "another machine, or changed)")
    return lines


def _matmul_rates(device: str) -> autotune.MatmulRates:
    return autotune.matmul_rates(resolve_device(device))


def _datasets_made(datasets: Iterable[tuple[str, str]], seed: int, data_root: Path) -> bool:
    """Whether every (domain, tier) dataset is complete under `data_root` (its metadata is written last)."""
    return all(dataset_complete(dataset_path(domain, tier, seed, data_root)) for domain, tier in datasets)


STRESSED = "stress tests of"  # the status of a stress run whose model another sweep trained


def unstressed_key(run: PlannedRun, data_root: Path) -> str | None:
    """The key of the run that trains `run`'s model without stress-testing it (None: `run` runs no stress
    test), so that a stress sweep tests a domain sweep's checkpoint instead of training the model again."""
    if not run.config.stress.enabled:
        return None
    return dataset_run_key(dataclasses.replace(run, config=dataclasses.replace(run.config, stress=StressConfig())),
                           data_root)


def format_plan(sweep: SweepSpec, tier: str, runs: list[PlannedRun], status: dict[str, str],
                columns: dict[str, dict[str, str]] | None = None) -> str:
    """The table of runs and their status; `columns`: more columns, header -> cell by run name."""
    columns = columns or {}
    header = ["#", "run", *[axis.split(".")[-1] for axis in sweep.axes], "seed", "dataset", "status", *columns]
    rows = [[str(i), r.name, *[str(r.axes[a]) for a in sweep.axes], str(r.seed),
             f"{r.training_domain}-{r.dataset_tier}-s{r.dataset_seed}"
             + (f" (tested on {r.domain}-{r.evaluated_on})" if r.evaluated_elsewhere else ""),
             status.get(r.name, ""), *[cells.get(r.name, "") for cells in columns.values()]]
            for i, r in enumerate(runs)]
    widths = [max(len(row[c]) for row in [header, *rows]) for c in range(len(header))]
    lines = [f"sweep {sweep.name} (tier {tier}, MLflow experiment '{sweep.experiment}'): {len(runs)} runs"]
    for row in [header, *rows]:
        lines.append("  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip())
    return "\n".join(lines)


@dataclass
class SweepStart:
    """What a sweep has before anything trains (`start_sweep`): the outcomes of the runs it needs not train
    (finished, shared, stress-tested, evaluated again, waiting for another kind of machine), the runs still to
    train in its order, the branches whose checkpoint is not ready yet (trainable once it is: their caller
    trains them then, or records them with `waiting_outcome`), and `keep`, which records a run that ends into
    the sweep's run summary."""

    outcomes: list[RunOutcome]
    pending: list[PlannedRun]
    keep: Callable[[RunOutcome | str], None]
    branches: list[PlannedRun] = dataclasses.field(default_factory=list)


def waiting_outcome(run: PlannedRun, runs_root: Path) -> RunOutcome:
    """A branch's outcome while the checkpoint it starts from is not ready."""
    return RunOutcome(run.name, "WAITING", error=f"{WAITS_FOR_TRUNK} {branch_checkpoint(run.config, runs_root)}")


def ready_branches(branches: list[PlannedRun], runs_root: Path) -> list[PlannedRun]:
    """Those of `branches` whose checkpoint is ready now (`trunk_ready`)."""
    return [run for run in branches if trunk_ready(branch_checkpoint(run.config, runs_root))]


def start_sweep(sweep: SweepSpec, tier: str, *, data_root: Path = Path("data"), runs_root: Path = Path("runs"),
                progress: bool = True, share: bool = True, only: Sequence[str] = (), train: bool = True,
                reevaluate_reason: str | None = None, reports_root: Path | None = None,
                echo: Callable[[str], None] = print, any_kind: bool = False,
                planned: tuple[list[PlannedRun], dict[str, str], dict[str, tuple[str, tracking.RunRecord]]]
                | None = None) -> SweepStart:
    """Everything `run_sweep` does before it trains: plan the runs (`prepare`, which makes their missing
    datasets; `planned`: its result, taken by the caller with the same settings), evaluate the finished ones
    again (`reevaluate_reason`), record the shared and stress-tested ones, and put what finished into the
    sweep's run summary; the runs left to train, unless `train` is off."""
    runs, status, shared = planned or prepare(sweep, tier, data_root, progress=progress, share=share, only=only,
                                              reports_root=reports_root, any_kind=any_kind, runs_root=runs_root)
    again: list[RunOutcome] = []
    if reevaluate_reason is not None:
        finished = [r for r in runs if status[r.name] == FINISHED]  # a summary's run has no checkpoint here
        echo(f"sweep {sweep.name} (tier {tier}): evaluating {len(finished)} finished runs again")
        again = reevaluate(sweep, finished, data_root, runs_root, reason=reevaluate_reason, progress=progress,
                           echo=echo)
    pending = [r for r in runs if status[r.name] == "to run"]
    done_again = {o.name for o in again}
    outcomes = again + [RunOutcome(r.name, "SKIPPED") for r in runs
                        if status[r.name] in (FINISHED, SUMMARISED) and r.name not in done_again]
    branches = [r for r in runs if status[r.name].startswith(WAITS_FOR_TRUNK)]
    waiting = [RunOutcome(r.name, "WAITING", error=status[r.name]) for r in runs
               if status[r.name].startswith((cpu_kinds.WAITS, WAITS_FOR_TRUNK))]
    selected = f" (--only {' '.join(only)})" if only else ""
    summarised = sum(status[r.name] == SUMMARISED for r in runs)
    echo(f"sweep {sweep.name} (tier {tier}){selected}: {len(runs)} runs, {len(outcomes)} already finished"
         + (f" ({summarised} known only from the committed run summary)" if summarised else "")
         + f", {len(shared)} shared with other sweeps, {len(pending)} to run" + ("" if train else ", not trained")
         + (f", {len(waiting)} waiting" if waiting else ""))
    for outcome in waiting:
        echo(f"  {outcome.name}: {outcome.error}"
             + ("; --any-cpu-kind trains it here" if outcome.error.startswith(cpu_kinds.WAITS) else ""))
    for line in changed_data(sweep, tier, runs, status, data_root, reports_root):
        echo(line)
    outcomes += [o for o in waiting if not o.error.startswith(WAITS_FOR_TRUNK)]
    if not train:
        pending = []
        outcomes += [o for o in waiting if o.error.startswith(WAITS_FOR_TRUNK)]
        branches = []

    def keep(outcome: RunOutcome | str) -> None:  # each finished run into the sweep's summary as it ends
        if reports_root is not None and isinstance(outcome, RunOutcome) and outcome.status in RECORDED:
            summarise(sweep, tier, reports_root, [outcome.run_id])

    if reports_root is not None:
        summarise_finished(sweep, tier, reports_root, [r.name for r in runs if status[r.name] == FINISHED])
    for outcome in again:
        keep(outcome)
    for run in runs:
        if run.name in shared and status[run.name].startswith(STRESSED):
            key, source = shared[run.name]
            echo(f"  {run.name}: {status[run.name]} (run {source.run_id}), its checkpoint stress-tested")
            outcomes.append(stress_trained_run(run, key, source, data_root, runs_root, progress))
            keep(outcomes[-1])
        elif run.name in shared:
            key, source = shared[run.name]
            where = f", from {source.tags[RESTORED_FROM]}" if RESTORED_FROM in source.tags else ""
            echo(f"  {run.name}: {status[run.name]} (run {source.run_id}{where}), recorded without training")
            outcomes.append(share_run(run, key, source))
            keep(outcomes[-1])
    return SweepStart(outcomes, pending, keep, branches)


def run_sweep(sweep: SweepSpec, tier: str, *, data_root: Path = Path("data"), runs_root: Path = Path("runs"),
              launcher: str = "local", cluster: str | None = None, progress: bool = True, share: bool = True,
              only: Sequence[str] = (), train: bool = True, reevaluate_reason: str | None = None,
              parallel: int = 1, reports_root: Path | None = None,
              echo: Callable[[str], None] = print,
              after_run: Callable[[RunOutcome, int], None] | None = None,
              any_kind: bool = False) -> list[RunOutcome]:
    """Run what the sweep lacks at this tier: its runs matching `only` (shell patterns over run names),
    or all. `share=False` trains runs another sweep already trained; `train=False` only records those.
    `reevaluate_reason`: first evaluate the finished runs again (`reevaluate`), saying why. `parallel`: with
    the local launcher, that many runs at once, each in its own process on its own share of the cores (on a
    GPU, sharing the device). `reports_root`: where the run summaries are read, and where each run that
    finishes (trained, shared, stress-tested, evaluated again) is recorded in its sweep's summary as it ends,
    with the finished runs MLflow holds that the summary lacks (none: MLflow only). `after_run(outcome,
    runs_left)`: called as each run the local launcher trains one at a time ends, with how many of this
    call's runs are still to train. A run held to another kind of machine (`sweep/cpu_kinds.py`) is not
    trained here (outcome WAITING, saying which kind), unless `any_kind`. A branch whose checkpoint is not
    ready (`train.init_from`) trains after the rest once one of them has made it ready (a trunk and its
    branches in one sweep: one call), or ends WAITING."""
    if parallel < 1:
        raise ValueError(f"parallel: expected at least 1 run at a time, got {parallel}")
    if parallel > 1 and launcher != "local":
        raise ValueError(f"parallel = {parallel} is for the local launcher; {launcher} sets its own parallelism")
    begun = start_sweep(sweep, tier, data_root=data_root, runs_root=runs_root, progress=progress, share=share,
                        only=only, train=train, reevaluate_reason=reevaluate_reason, reports_root=reports_root,
                        echo=echo, any_kind=any_kind)
    outcomes, keep = begun.outcomes, begun.keep

    def train_runs(pending: list[PlannedRun]) -> list[RunOutcome]:
        if launcher == "local" and parallel > 1:
            from gns_bench.sweep.launchers import run_parallel

            echo(f"  {min(parallel, len(pending))} runs at a time, each in its own process on its own cores; "
                 f"each run's progress in {run_dir(runs_root, pending[0]).parent}/<run>/{PROGRESS_LOG}"
                 if pending else "  nothing to run")
            job = partial(execute_run, data_root=data_root.resolve(), runs_root=runs_root.resolve(),
                          tracking_uri=tracking.tracking_uri(), progress=False, progress_log=progress)
            results = run_parallel(job, pending, parallel, echo, on_result=keep)
            return [as_outcome(run, result) for run, result in zip(pending, results, strict=True)]
        if launcher == "local":
            trained = []
            for index, run in enumerate(pending, 1):
                echo(f"[{index}/{len(pending)}] {run.name}")
                outcome = execute_run(run, data_root, runs_root, progress=progress)
                if outcome.status == "FAILED":
                    echo(f"  FAILED: {outcome.error}")
                trained.append(outcome)
                keep(outcome)
                if after_run is not None:
                    after_run(outcome, len(pending) - index)
            return trained
        if launcher == "submitit":
            from gns_bench.sweep.launchers import submit

            job = partial(execute_run, data_root=data_root.resolve(), runs_root=runs_root.resolve(),
                          tracking_uri=tracking.tracking_uri(), progress=False)
            results = submit(job, pending, runs_root / sweep.name / tier / "submitit", cluster)
            for result in results:
                keep(result)
            return [as_outcome(run, result) for run, result in zip(pending, results, strict=True)]
        raise ValueError(f"unknown launcher {launcher!r}; expected 'local' or 'submitit'")

    outcomes += train_runs(begun.pending)
    branches = begun.branches
    while ready := ready_branches(branches, runs_root):  # a trunk this call trained: its branches now
        echo(f"  {len(ready)} branch(es) whose checkpoint is now ready: {', '.join(r.name for r in ready)}")
        branches = [run for run in branches if run not in ready]
        outcomes += train_runs(ready)
    outcomes += [waiting_outcome(run, runs_root) for run in branches]
    return outcomes
