"""What a report keeps of what it drew: `reports/<sweep>/<tier>/report.json` beside its README.

A report reads the runs' records (`sweep/summaries.py`, written by the runner) and MLflow; what it takes from
MLflow and would lose with the store (which rollouts its pictures show, the stress tests' per-trajectory
results, the baselines' failure pictures and measured costs, the unfinished runs it showed, which the runner's
summary does not hold) it keeps here, so that it is
rebuilt the same on a machine without that store. A summary written before the runner wrote the records
holds these under its `extras`; they are read from there while no `report.json` exists.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from gns_bench.sweep.summaries import SUMMARY_FILE

KEPT_FILE = "report.json"
UNFINISHED = "unfinished"  # the unfinished runs a report showed, by run name (`collect.unfinished_records`)
NOTE = "written by gns-bench report: what its pictures and tables took from the runs' artifacts"


def read_kept(report_dir: Path) -> dict[str, Any]:
    """The report's kept data (empty when there is none). A file that is not JSON reads as empty: what it
    held is drawn again from MLflow where the store still has it."""
    for path, key in ((Path(report_dir) / KEPT_FILE, "kept"), (Path(report_dir) / SUMMARY_FILE, "extras")):
        if path.is_file():
            try:
                return dict(json.loads(path.read_text()).get(key) or {})
            except (ValueError, AttributeError):
                return {}
    return {}


def write_kept(report_dir: Path, sweep: str, tier: str, kept: dict[str, Any], note: str = NOTE) -> Path | None:
    """Keep `kept` for the report at `report_dir`: written whole (through a temporary file) when there is
    something to keep or a file to replace; nothing written otherwise."""
    path = Path(report_dir) / KEPT_FILE
    if not kept and not path.exists():
        return None
    payload = {"sweep": sweep, "tier": tier, "note": note, "kept": kept}
    partial = path.with_name(f".{KEPT_FILE}.partial")
    partial.write_text(json.dumps(payload, indent=1, sort_keys=True, allow_nan=True) + "\n")
    os.replace(partial, path)
    return path
