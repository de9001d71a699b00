"""Durations as reports and plans print them: seconds under 90 s, minutes under 90 min, hours above."""

from __future__ import annotations


def format_duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
