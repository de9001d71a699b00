"""Checkpoints: written atomically (temporary file, then rename), so a crash never leaves a torn one; and the
simulator rebuilt from one (its config and the dataset's normalisation travel with it)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from gns_bench import simulators
from gns_bench.config import Config, resolve_for_dataset, saved_config
from gns_bench.data.format import Metadata
from gns_bench.devices import resolve_device
from gns_bench.model.simulator import LearnedSimulator, Simulator
from gns_bench.train.averaging import averaged

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


def build_simulator(config: Config, metadata: Metadata) -> Simulator:
    """A fresh simulator of `config.model.architecture` (the config resolved against `metadata` if it is not
    yet) on that dataset: the paper's GNS, or a baseline it is compared with (Sec. 5.5)."""
    config = resolve_for_dataset(config, metadata.default_connectivity_radius)
    return simulators.build(config, metadata)


def load_simulator(checkpoint: str | Path, device: str | torch.device = "cpu"
                   ) -> tuple[LearnedSimulator, Config, Metadata]:
    """Rebuild a trained simulator from its checkpoint, in eval mode on `device` ("auto" allowed): with its
    weights' average where it trained with one (`train.weight_average`), the model its run is tested as. Its config
    is resolved against the dataset it was trained on (checkpoints from before configs were resolved hold
    no radius) and reads fields it predates as they were (`config.saved_config`)."""
    device = resolve_device(str(device))
    saved = load_checkpoint(checkpoint, device)
    metadata = Metadata.from_json(saved["metadata"], f"{checkpoint} (metadata)")
    config = resolve_for_dataset(saved_config(saved["config"], str(checkpoint)), metadata.default_connectivity_radius)
    simulator = build_simulator(config, metadata).to(device)
    simulator.load_state_dict(averaged(saved["model"], saved.get("average")))  # a run's model: its average
    simulator.eval()
    return simulator, config, metadata
