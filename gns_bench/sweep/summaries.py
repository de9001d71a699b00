"""Run summaries: the compact record of a sweep's runs committed beside its report.

`reports/<sweep>/<tier>/runs.json` holds each run's params, final metrics, tags (its `run_key`, dataset hash,
hardware, timing) and training curves, and `extras`: what else its report showed that MLflow's artifacts held.
`gns-bench report` writes it and rebuilds the tables from it when the MLflow store that made the runs is gone;
the sweep runner reads it to know which runs are done in such a store (`sweep/runner.py`), so a campaign
resumed on a new machine does not train again what the repository already reports.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from gns_bench import tracking

SUMMARY_FILE = "runs.json"
RESTORED_FROM = "restored_from"  # the tag a record read from a summary carries: the file it came from


def summary_path(reports_root: Path, sweep: str, tier: str) -> Path:
    return Path(reports_root) / sweep / tier / SUMMARY_FILE


DEFAULT_NOTE = "written by gns-bench report; read back by it when MLflow no longer holds these runs"


def write_run_summary(path: Path, sweep: str, tier: str, records: Iterable[tracking.RunRecord],
                      extras: dict[str, Any] | None = None, note: str = DEFAULT_NOTE) -> Path:
    """The runs as JSON (sorted by run name), `extras` (e.g. which rollouts the report drew) and a `note` on
    what wrote the file."""
    runs = [dataclasses.asdict(r) for r in sorted(records, key=lambda r: r.name)]
    payload = {"sweep": sweep, "tier": tier, "note": note, "runs": runs, "extras": extras or {}}
    path.write_text(json.dumps(payload, indent=1, sort_keys=True, allow_nan=True) + "\n")
    return path


def read_summary_extras(path: Path) -> dict[str, Any]:
    if not path.is_file():
        return {}
    try:
        return dict(json.loads(path.read_text()).get("extras", {}))
    except ValueError:
        return {}


def read_run_summary(path: Path) -> dict[str, tracking.RunRecord]:
    """A committed run summary by run name; empty when there is none. A file that is not one raises
    ValueError naming it."""
    if not path.is_file():
        return {}
    try:
        runs = json.loads(path.read_text())["runs"]
        records = [tracking.RunRecord(**{**run, "curves": {k: [tuple(p) for p in v]
                                                           for k, v in run.get("curves", {}).items()}})
                   for run in runs]
    except (ValueError, KeyError, TypeError) as exc:
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
