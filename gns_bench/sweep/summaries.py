"""Run summaries: the compact record of a sweep's runs, committed beside its report.

`reports/<sweep>/<tier>/runs.json` holds each finished run's params, final metrics, tags (its `run_key`, dataset
hash, hardware, timing) and training curves. The sweep runner writes it as each run finishes
(`sweep/runner.py`, `record_runs`), and reads it to know which runs are done in a store that lacks them, so a
campaign resumed on a new machine does not train again what the repository already holds; the reports read
it (beside MLflow) and rebuild from it when the MLflow store that made the runs is gone. What a report keeps
of its own (which rollouts it drew) is `report/kept.py`'s.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from gns_bench import tracking

SUMMARY_FILE = "runs.json"
RESTORED_FROM = "restored_from"  # the tag a record read from a summary carries: the file it came from


def summary_path(reports_root: Path, sweep: str, tier: str) -> Path:
    return Path(reports_root) / sweep / tier / SUMMARY_FILE


DEFAULT_NOTE = ("written by gns-bench sweep as each run finished; read back by it and by the reports when MLflow "
                "no longer holds these runs")


def write_run_summary(path: Path, sweep: str, tier: str, records: Iterable[tracking.RunRecord],
                      note: str = DEFAULT_NOTE, extras: dict[str, Any] | None = None) -> Path:
    """The runs as JSON (sorted by run name) with a `note` on what wrote the file, written whole through a
    temporary file (an interrupted write leaves the old summary). `extras`: the report's kept data of a
    summary written before reports kept their own (`report/kept.py`), carried over unchanged."""
    runs = [dataclasses.asdict(r) for r in sorted(records, key=lambda r: r.name)]
    payload: dict[str, Any] = {"sweep": sweep, "tier": tier, "note": note, "runs": runs}
    if extras:
        payload["extras"] = extras
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    partial.write_text(json.dumps(payload, indent=1, sort_keys=True, allow_nan=True) + "\n")
    os.replace(partial, path)
    return path


def record_runs(path: Path, sweep: str, tier: str, records: Iterable[tracking.RunRecord]) -> list[str]:
    """Put FINISHED `records` into the summary at `path` (created if missing), each replacing the record of
    its run name; the other runs stay as they were. Returns the names written (none when every record was
    already there as it is)."""
    payload = _read(path)
    held = _records(path, payload)
    fresh = [r for r in records
             if r.status == "FINISHED" and (r.name not in held or _as_json(held[r.name]) != _as_json(r))]
    if not fresh:
        return []
    held.update({r.name: r for r in fresh})
    write_run_summary(path, sweep, tier, held.values(), extras=payload.get("extras"))
    return [r.name for r in fresh]


def _as_json(record: tracking.RunRecord) -> str:
    """A record as the summary writes it (NaN equal to NaN, tuples to lists)."""
    return json.dumps(dataclasses.asdict(record), sort_keys=True, allow_nan=True)


def record_from_json(run: dict[str, Any]) -> tracking.RunRecord:
    """A record as a summary holds it (its curves' points as lists) back as a `RunRecord`."""
    return tracking.RunRecord(**{**run, "curves": {k: [tuple(p) for p in v] for k, v in run.get("curves", {}).items()}})


def read_run_summary(path: Path) -> dict[str, tracking.RunRecord]:
    """A committed run summary by run name; empty when there is none. A file that is not one raises
    ValueError naming it."""
    return _records(path, _read(path))


def _read(path: Path) -> dict[str, Any]:
    """The summary file's JSON ({} when there is none); ValueError naming it when it is not JSON."""
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ValueError(f"{path}: not a gns-bench run summary ({type(exc).__name__}: {exc})") from None


def _records(path: Path, payload: dict[str, Any]) -> dict[str, tracking.RunRecord]:
    if not payload:
        return {}
    try:
        records = [record_from_json(run) for run in payload["runs"]]
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a gns-bench run summary ({type(exc).__name__}: {exc})") from None
    return {record.name: record for record in records}


def summarised_runs(reports_root: Path, tier: str | None = None) -> list[tracking.RunRecord]:
    """Every FINISHED run that the summaries under `reports_root` hold (at `tier`, or at every tier), each
    tagged `restored_from` with its file. Its artifacts (checkpoint, rollouts) are not here."""
    records = []
    for path in sorted(Path(reports_root).glob(f"*/{tier or '*'}/{SUMMARY_FILE}")):
        for record in read_run_summary(path).values():
            if record.status == "FINISHED":
                record.tags = {**record.tags, RESTORED_FROM: str(path)}
                records.append(record)
    return records
