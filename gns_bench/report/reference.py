"""The paper's reference numbers, read from ONE place each: the domain specs for the paper's Table 1
(`datasets/<id>.toml [paper]`), `paper_reference.toml` beside this file for the rest (ablation defaults,
CConv comparisons, inference times, the training budget)."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

REFERENCE_FILE = Path(__file__).with_name("paper_reference.toml")


@dataclass(frozen=True)
class DomainReference:
    """A domain as the paper reports it (Table 1), plus its CConv figure where Sec. 5.5 gives one."""

    id: str
    name: str
    simulator: str
    dim: int
    max_particles: int
    sequence_length: int
    one_step_mse: float
    rollout_mse: float
    cconv_rollout_mse: float | None


@cache
def paper_reference() -> dict[str, Any]:
    return tomllib.loads(REFERENCE_FILE.read_text())


def paper_training_steps() -> int:
    return int(paper_reference()["training"]["steps"])


def ablation_reference(axis: str) -> dict[str, Any]:
    """{"default": value, "scale": "log"|"linear"|"category"}; unknown axes get no default, linear scale."""
    return dict(paper_reference()["ablations"].get(axis, {"scale": "linear"}))


def inference_reference(dim: int, simulator: str) -> dict[str, Any] | None:
    """The App. C.6 timing range covering a domain of this dimension and simulator (e.g. "MPM (2D)"), if any."""
    return next((row for row in paper_reference()["inference"]
                 if row["dim"] == dim and any(s in simulator for s in row["simulators"])), None)


def domain_reference(domain_id: str) -> DomainReference | None:
    """The paper's row for a domain id (None for domains the paper lacks, such as `tiny`)."""
    from gns_bench.physics.spec import load_domain_spec

    try:
        spec = load_domain_spec(domain_id)
    except Exception:  # noqa: BLE001 - no spec (tiny, a test domain) or one being edited: no reference row
        return None
    paper = spec.paper
    cconv = paper_reference()["cconv_rollout_mse"].get(domain_id)
    return DomainReference(domain_id, spec.name, paper.simulator, spec.dim, paper.max_particles,
                           paper.sequence_length, paper.one_step_mse, paper.rollout_mse, cconv)


@dataclass(frozen=True)
class BaselineFailure:
    """A domain where the paper shows a baseline failing (Sec. 5.5; `[baseline_failures]`)."""

    domain: str
    words: str  # what the paper saw, as a clause
    rigidity: bool  # the domain holds a rigid body whose rigidity drift is drawn


def baseline_failures() -> tuple[BaselineFailure, ...]:
    """Every `[baseline_failures.<domain>]` entry, in the file's order."""
    return tuple(BaselineFailure(domain, str(entry["words"]), bool(entry["rigidity"]))
                 for domain, entry in paper_reference()["baseline_failures"].items())


def display_name(domain_id: str) -> str:
    """The domain as the paper names it (Table 1), or its id where the paper lacks it."""
    ref = domain_reference(domain_id)
    return ref.name if ref else domain_id


def baseline_rollout_mse(reference, architecture: str) -> float | None:
    """The paper's rollout MSE of a baseline architecture on a domain, where it reports one (CConv's, read off
    Fig. 5's bar chart: `<architecture>_rollout_mse` in paper_reference.toml); None otherwise."""
    value = getattr(reference, f"{architecture}_rollout_mse", None) if reference is not None else None
    return value or None
