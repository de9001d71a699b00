"""What a stress test returns: plain data (no model, no torch), so the stability report and the figures can
read results back from a run's `stress/<test>.json` without loading a simulator."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class StressResult:
    name: str
    metrics: dict[str, float] = field(default_factory=dict)
    curves: dict[str, list[float]] = field(default_factory=dict)  # per rollout step, NaN where not reached
    trips: list[str] = field(default_factory=list)  # "<scene> trajectory i: <monitor> at step k: ..."
    notes: list[str] = field(default_factory=list)
