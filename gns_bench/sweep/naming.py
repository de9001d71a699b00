"""What a sweep file is called and what kind of experiment it is, from where it sits under `sweeps/`.

`sweeps/domains/goop.toml` is sweep `domain-goop` of kind "domain"; `sweeps/ablations/noise_std.toml` is
`ablation-noise_std`, kind "ablation"; `sweeps/studies/learning_rate_decay.toml` is
`study-learning_rate_decay`, kind "study". A folder not listed in SWEEP_KINDS names its kind by itself, a
final 's' dropped (not 'ss'): `sweeps/tests/x.toml` is `test-x`.

Standard library only: noxfile.py loads this file by path to name its sessions before gns_bench is
installed, so the rule is written once.
"""

from __future__ import annotations

from pathlib import Path

SWEEP_KINDS = {"domains": "domain", "ablations": "ablation", "stress": "stress", "studies": "study",
               "baselines": "baseline"}
NOT_SWEEPS = ("tiers.toml", "campaigns")  # the shared tier budgets, and the folder of campaign files


def is_sweep_file(path: Path, sweeps_dir: Path) -> bool:
    """A TOML under `sweeps_dir` that is a sweep: not the tier budgets, not a campaign."""
    try:
        parts = path.resolve().relative_to(sweeps_dir.resolve()).parts
    except ValueError:
        return True  # a sweep file given by path from elsewhere
    return path.suffix == ".toml" and not any(part in NOT_SWEEPS for part in parts)


def sweep_kind(path: Path, sweeps_dir: Path) -> str:
    """The kind of the sweep file at `path` ("" for a file directly in `sweeps_dir` or outside it)."""
    try:
        relative = path.resolve().relative_to(sweeps_dir.resolve())
    except ValueError:
        return ""
    folder = relative.parts[0] if len(relative.parts) > 1 else ""
    return SWEEP_KINDS.get(folder, folder[:-1] if folder.endswith("s") and not folder.endswith("ss") else folder)


def sweep_name(path: Path, sweeps_dir: Path) -> str:
    """`<kind>-<file stem>`, or the stem alone when the file has no kind."""
    kind = sweep_kind(path, sweeps_dir)
    return f"{kind}-{path.stem}" if kind else path.stem
