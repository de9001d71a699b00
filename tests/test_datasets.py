"""The one entry point for datasets by domain id: `tiny`, a physics domain or a variant."""

from __future__ import annotations

from pathlib import Path

import pytest

from gns_bench.cli import main
from gns_bench.datasets import dataset_path, ensure_dataset, list_domains
from gns_bench.physics.spec import UnknownDomainError


def test_unknown_domain_names_it_and_lists_every_domain(tmp_path: Path) -> None:
    with pytest.raises(UnknownDomainError) as info:
        ensure_dataset("notadomain", "smoke", 0, tmp_path)
    message = str(info.value)
    assert message.startswith("unknown domain 'notadomain'")
    assert info.value.domains == list_domains() and info.value.domains[0] == "tiny"
    assert all(domain in message for domain in ("tiny", "waterdrop", "sand-3d", "boxbath", "waterramps-inflow"))
    assert not any(tmp_path.iterdir())  # nothing made for it


def test_generate_command_reports_an_unknown_domain(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["generate", "notadomain"]) == 2
    err = capsys.readouterr().err
    assert "unknown domain 'notadomain'" in err and "<file>" not in err
    assert all(domain in err for domain in ("tiny", "waterdrop", "sand-3d"))
    assert not any(tmp_path.iterdir())


def test_tiny_is_generated_once_then_reused(tmp_path: Path) -> None:
    path = ensure_dataset("tiny", "smoke", 0, tmp_path)
    assert path == dataset_path("tiny", "smoke", 0, tmp_path) and (path / "metadata.json").is_file()
    stamp = (path / "metadata.json").stat().st_mtime_ns
    assert ensure_dataset("tiny", "smoke", 0, tmp_path) == path
    assert (path / "metadata.json").stat().st_mtime_ns == stamp
