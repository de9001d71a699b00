"""An untrained small GNS on the tiny dataset: what the rollout, inflow and cost tests drive."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gns_bench.config import ModelConfig
from gns_bench.data.format import read_metadata
from gns_bench.model.simulator import LearnedSimulator


@pytest.fixture(scope="module")
def untrained(tiny_dataset: Path) -> LearnedSimulator:
    torch.manual_seed(0)
    meta = read_metadata(tiny_dataset)
    config = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=2,
                         connectivity_radius=meta.default_connectivity_radius)
    return LearnedSimulator(config, meta, 3e-4).eval()
