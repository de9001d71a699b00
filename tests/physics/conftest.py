"""Shared by the physics tests: smoke-tier datasets made once per session, and runs at several thread counts."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Sequence
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


def _digests_across_threads(script: str, threads: Sequence[str]) -> set[str]:
    """Run `script` (which prints a digest on its last line) in a fresh CPU process per thread count and
    collect the digests: a deterministic solver gives one."""
    digests = set()
    for count in threads:
        env = {**os.environ, "GNS_BENCH_TAICHI_THREADS": count, "GNS_BENCH_TAICHI_ARCH": "cpu"}
        out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
        digests.add(out.stdout.strip().splitlines()[-1])
    return digests


@pytest.fixture
def digests_across_threads() -> Callable[[str, Sequence[str]], set[str]]:
    return _digests_across_threads
