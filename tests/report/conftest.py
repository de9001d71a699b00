"""Fixtures shared by the report tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def smoke_model() -> str:
    """The smoke tier's model for the sweeps these tests run for real: one message-passing step of width 8,
    so a run takes seconds. A TOML block to put in a sweep file."""
    return ("\n[tiers.smoke.config.model]\n"
            "latent_size = 8\n"
            "mlp_hidden_size = 8\n"
            "message_passing_steps = 1\n")
