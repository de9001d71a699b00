"""Checkpoints: written atomically (temporary file, then rename), so a crash never leaves a torn one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

CHECKPOINT_NAME = "checkpoint.pt"
FORMAT_VERSION = 1


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format_version": FORMAT_VERSION, **state}, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint there")
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:
        raise ValueError(f"{path}: unreadable or truncated checkpoint ({exc})") from exc
    for key in ("format_version", "model", "config", "metadata", "step"):
        if key not in state:
            raise ValueError(f"{path}: not a gns-bench checkpoint (missing '{key}')")
    if state["format_version"] != FORMAT_VERSION:
        raise ValueError(f"{path}: checkpoint format {state['format_version']}, expected {FORMAT_VERSION}")
    return state
