"""Campaign files: `sweeps/campaigns/<name>.toml` lists sweep files (relative to `sweeps/`) in the order they
should fill in. Read here, by the campaign runner (`gns_bench/campaign.py`) and by the front page,
which states what the campaign has cost so far (`report/index.py`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from gns_bench.config import read_toml
from gns_bench.sweep.spec import SWEEPS_DIR, SweepError, load_sweep, reject_unknown_keys

CAMPAIGNS_DIR = SWEEPS_DIR / "campaigns"
_KEYS = {"description", "sweeps"}


@dataclass(frozen=True)
class Campaign:
    name: str
    path: Path
    description: str
    sweeps: tuple[Path, ...]  # in priority order


def load_campaign(path: str | Path, sweeps_dir: Path = SWEEPS_DIR) -> Campaign:
    """A campaign file, every sweep it names checked to exist and load."""
    path = Path(path)
    data = read_toml(path, SweepError)
    reject_unknown_keys(data, _KEYS, path)
    names = data.get("sweeps")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise SweepError(f"{path}: 'sweeps': expected a non-empty list of sweep files relative to {sweeps_dir}")
    if len(set(names)) != len(names):
        raise SweepError(f"{path}: 'sweeps': {sorted({n for n in names if names.count(n) > 1})} listed twice")
    sweeps = tuple(sweeps_dir / name for name in names)
    for name, sweep in zip(names, sweeps, strict=True):
        if not sweep.is_file():
            raise SweepError(f"{path}: 'sweeps': no sweep file {name} in {sweeps_dir}")
        load_sweep(sweep, sweeps_dir)  # a broken sweep fails here, before anything runs
    return Campaign(path.stem, path, str(data.get("description", "")), sweeps)
