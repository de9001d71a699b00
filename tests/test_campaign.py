"""A campaign runs its sweeps in order, goes on past a failing one, resumes, and writes every report."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from gns_bench.campaign import load_campaign, run_campaign
from gns_bench.sweep.spec import SWEEPS_DIR, SweepError

SWEEP = '''description = "{name}"
domain = "tiny"

[tiers.smoke.config.model]
latent_size = 8
mlp_hidden_size = 8
message_passing_steps = {steps}
'''


@pytest.fixture
def sweeps(tmp_path: Path) -> Path:
    root = tmp_path / "sweeps"
    for folder in ("domains", "ablations", "campaigns"):
        (root / folder).mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", root / "tiers.toml")
    (root / "domains" / "one.toml").write_text(SWEEP.format(name="first", steps=1))
    (root / "domains" / "two.toml").write_text(SWEEP.format(name="second", steps=2))
    return root


def test_campaign_runs_in_order_goes_on_past_a_failure_and_resumes(sweeps: Path, tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    path = sweeps / "campaigns" / "c.toml"
    path.write_text('sweeps = ["domains/two.toml", "domains/one.toml"]\n')
    campaign = load_campaign(path, sweeps)
    assert [p.stem for p in campaign.sweeps] == ["two", "one"]
    from gns_bench.sweep import runner

    real, order = runner.execute_run, []

    def first_fails(run, *args, **kwargs):
        order.append(run.sweep)
        if run.sweep == "domain-two" and len(order) == 1:
            raise RuntimeError("dataset on fire")  # a sweep that cannot run at all
        return real(run, *args, **kwargs)

    monkeypatch.setattr(runner, "execute_run", first_fails)
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", reports_root=tmp_path / "reports")
    results = run_campaign(campaign, "smoke", progress=False, echo=lambda line: None, sweeps_dir=sweeps, **roots)
    assert order == ["domain-two", "domain-one"]  # the campaign's order, and it went on past the failure
    assert results[0].error.startswith("RuntimeError: dataset on fire") and results[1].outcomes[0].status == "FINISHED"
    assert (tmp_path / "reports" / "domain-one" / "smoke" / "README.md").is_file()  # written when it was done
    assert (tmp_path / "reports" / "domains" / "smoke" / "README.md").is_file()  # and every report at the end
    again = run_campaign(campaign, "smoke", progress=False, echo=lambda line: None, sweeps_dir=sweeps, **roots)
    assert [o.status for r in again for o in r.outcomes] == ["FINISHED", "SKIPPED"]  # resumed: only what lacked


def test_a_campaign_naming_a_missing_sweep_fails_before_running(sweeps: Path) -> None:
    path = sweeps / "campaigns" / "bad.toml"
    path.write_text('sweeps = ["domains/one.toml", "domains/nope.toml"]\n')
    with pytest.raises(SweepError, match="no sweep file domains/nope.toml"):
        load_campaign(path, sweeps)


def test_the_paper_campaign_lists_every_domain_then_the_ablations() -> None:
    campaign = load_campaign(SWEEPS_DIR / "campaigns" / "paper.toml")
    folders = [p.parent.name for p in campaign.sweeps]
    assert folders == ["domains"] * 16 + ["ablations"] * 12 + ["baselines"] * 7
    assert [p.stem for p in campaign.sweeps[16:22]] == ["message_passing_steps", "connectivity_radius", "noise_std",
                                                         "processor_sharing", "position_encoding", "noise_correction"]
