"""Smoke-tier datasets generated once per test session and shared by the physics tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from gns_bench.physics.generate import generate_dataset


@pytest.fixture(scope="session")
def smoke_dataset(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    root = tmp_path_factory.mktemp("smoke")
    cache: dict[str, Path] = {}

    def get(domain: str) -> Path:
        if domain not in cache:
            cache[domain] = generate_dataset(domain, "smoke", seed=0, out=root / domain, progress=False)
        return cache[domain]

    return get
