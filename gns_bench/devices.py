"""Where torch runs: the device a run asks for, resolved once."""

from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """`"auto"` picks CUDA when present, else the CPU; any other name is torch's."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)
