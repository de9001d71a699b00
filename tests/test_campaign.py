"""A campaign runs its sweeps in order, goes on past a failing one, resumes, and writes every report."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from gns_bench.campaign import plan_campaign, run_campaign
from gns_bench.datasets import ensure_dataset
from gns_bench.evaluate.cost import EvaluationCost
from gns_bench.sweep.campaigns import load_campaign
from gns_bench.sweep.spec import SWEEPS_DIR, SweepError, load_sweep
from gns_bench.train.checkpoints import load_checkpoint
from gns_bench.train.rate import StepRate

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
    said: list[str] = []
    results = run_campaign(campaign, "smoke", progress=False, echo=said.append, sweeps_dir=sweeps, **roots)
    assert order == ["domain-two", "domain-one"]  # the campaign's order, and it went on past the failure
    assert results[0].error.startswith("RuntimeError: dataset on fire") and results[1].outcomes[0].status == "FINISHED"
    assert (tmp_path / "reports" / "domain-one" / "smoke" / "README.md").is_file()  # written when it was done
    reports = [line.split("report: ")[1] for line in said if line.startswith("  report: ")]
    overviews = [str(tmp_path / "reports" / page / "smoke" / "README.md")
                 for page in ("domains", "stability", "baselines")]
    # with the pages that read every sweep, so the reports agree at any point, before the final rewrite of all
    assert reports[:5] == [str(tmp_path / "reports" / "domain-one" / "smoke" / "README.md"), *overviews,
                           str(tmp_path / "reports" / "README.md")]
    assert (tmp_path / "reports" / "domains" / "smoke" / "README.md").is_file()  # and every report at the end
    from gns_bench.durations import format_duration
    from gns_bench.report.collect import collect
    from gns_bench.report.index import campaign_section

    half = collect(load_sweep(campaign.sweeps[1], sweeps), "smoke", tmp_path / "reports")[0]  # domain-one's run
    each = half.metric("train/wall_time_s") + half.metric("evaluation_seconds")
    partway = campaign_section(tmp_path / "reports", path, sweeps, tiers=("smoke",))[-2]
    assert partway.startswith("| smoke | 1 of 2 |") and f"| 1 model, about {format_duration(each)} |" in partway
    said.clear()
    again = run_campaign(campaign, "smoke", progress=False, echo=said.append, sweeps_dir=sweeps, **roots)
    assert [o.status for r in again for o in r.outcomes] == ["FINISHED", "SKIPPED"]  # resumed: only what lacked
    # the sweep that ran has its report written when done and again at the end; the one that ran nothing new
    # is written only in the final rewrite
    reports = [line.split("report: ")[1] for line in said if line.startswith("  report: ")]
    assert reports.count(str(tmp_path / "reports" / "domain-two" / "smoke" / "README.md")) == 2, reports
    assert reports.count(str(tmp_path / "reports" / "domain-one" / "smoke" / "README.md")) == 1, reports
    assert "  reports: unchanged, nothing new in domain-one" in said

    # a sweep whose summary was lost: its runs are skipped on resume, the runner records them again from
    # MLflow, and the report, now older than its summary, is written again
    from gns_bench.sweep.summaries import summary_path

    summary_path(tmp_path / "reports", "domain-one", "smoke").unlink()
    said.clear()
    third = run_campaign(campaign, "smoke", progress=False, echo=said.append, sweeps_dir=sweeps, **roots)
    assert [o.status for r in third for o in r.outcomes] == ["SKIPPED", "SKIPPED"]
    reports = [line.split("report: ")[1] for line in said if line.startswith("  report: ")]
    assert reports.count(str(tmp_path / "reports" / "domain-one" / "smoke" / "README.md")) == 2, reports
    assert "  reports: unchanged, nothing new in domain-one" not in said
    assert "  reports: unchanged, nothing new in domain-two" in said
    assert summary_path(tmp_path / "reports", "domain-one", "smoke").is_file()

    # the front page states what the campaign trained and what that cost, each model once
    lines = campaign_section(tmp_path / "reports", path, sweeps, tiers=("smoke",))
    rows = [r for p in campaign.sweeps for r in collect(load_sweep(p, sweeps), "smoke", tmp_path / "reports")]
    assert len(rows) == 2 and all(r.metric("evaluation_seconds") > 0 for r in rows)
    seconds = sum(r.metric("train/wall_time_s") for r in rows)
    assert lines[-2].startswith(f"| smoke | 2 of 2 | {seconds:.0f} s | ") and "| none |" in lines[-2], lines


def test_a_campaign_naming_a_missing_sweep_fails_before_running(sweeps: Path) -> None:
    path = sweeps / "campaigns" / "bad.toml"
    path.write_text('sweeps = ["domains/one.toml", "domains/nope.toml"]\n')
    with pytest.raises(SweepError, match="no sweep file domains/nope.toml"):
        load_campaign(path, sweeps)


def test_the_paper_campaign_lists_every_domain_then_the_ablations() -> None:
    campaign = load_campaign(SWEEPS_DIR / "campaigns" / "paper.toml")
    folders = [p.parent.name for p in campaign.sweeps]
    assert folders == ["domains"] * 16 + ["ablations"] * 12 + ["baselines"] * 7 + ["stress"] * 5
    assert [p.stem for p in campaign.sweeps[16:22]] == ["message_passing_steps", "connectivity_radius", "noise_std",
                                                         "processor_sharing", "position_encoding", "noise_correction"]


def test_a_timed_plan_measures_each_cost_once_and_counts_a_shared_point_once(sweeps: Path, tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    from gns_bench.sweep import timing

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")  # nothing trained yet
    (sweeps / "ablations" / "same.toml").write_text(SWEEP.format(name="the point of 'one'", steps=1))
    (sweeps / "stress").mkdir()
    (sweeps / "stress" / "one.toml").write_text(SWEEP.format(name="tests of 'one'", steps=1)
                                                + '\n[config.stress]\ntests = ["precision"]\n')
    path = sweeps / "campaigns" / "c.toml"
    path.write_text('sweeps = ["domains/one.toml", "domains/two.toml", "ablations/same.toml", "stress/one.toml"]\n')
    campaign = load_campaign(path, sweeps)
    measured = []

    def fake_rate(config, dataset_dir, steps, warm_up=5):
        measured.append(config.model.message_passing_steps)
        return StepRate(4.0 * config.model.message_passing_steps, "fp32", steps)  # M=1: 4 steps/s, M=2: 8

    def fake_evaluation(run, data_root):
        evaluated.append(run.config.model.message_passing_steps)
        return EvaluationCost(rollout_seconds=3.0 * run.config.model.message_passing_steps, rollout_steps=10,
                              one_step_seconds=0.5, distribution_seconds=0.5)  # M=1: 4 s, M=2: 7 s

    evaluated: list[int] = []
    monkeypatch.setattr(timing, "measure_step_rate", fake_rate)
    monkeypatch.setattr(timing, "measure_evaluation", fake_evaluation)
    lines: list[str] = []
    plan_campaign(campaign, "smoke", tmp_path / "data", lines.append, timed=True)
    assert measured == [] and lines[-1].endswith("to run: 0 runs, 0 s of training and 0 s of evaluation at the "
                                                  "rates measured here (and 4 runs whose dataset is not generated "
                                                  "yet, not timed)")
    ensure_dataset("tiny", "smoke", 0, tmp_path / "data", progress=False)
    lines.clear()
    plan_campaign(campaign, "smoke", tmp_path / "data", lines.append, timed=True)
    assert measured == [1, 2]  # 'same' and the stress sweep's model cost what 'one' costs: measured once
    assert evaluated == [1, 2]  # likewise their evaluations (the same eval config and evaluation data)
    first_row = "\n".join(lines).splitlines()[4]  # 'one': two timings, title, header, its run
    # steps/s, training time (20 smoke steps at 4/s), evaluation time and its rollout steps
    assert first_row.split()[-9:] == ["4", "(fp32)", "5", "s", "4", "s", "(10", "rollout", "steps)"], first_row
    # 20 steps at 4/s and at 8/s; 'same' is the run 'one' trains (the same key), so counted once, and the
    # stress sweep tests that run's model: no training of its own, and its stress rollouts are not counted
    assert lines[-1] == ("campaign c (smoke): to run: 2 runs, 8 s of training and 11 s of evaluation at the rates "
                         "measured here")


def test_a_campaign_in_lanes_keeps_both_lanes_busy_across_sweeps(sweeps: Path, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Two sweeps of one run each, two lanes: a lane makes the shared dataset first (the other sweep waits for
    it rather than making it a second time), then the second sweep's run trains beside the first's, where a
    campaign run sweep by sweep leaves one lane idle; each run's progress lands in its run directory, each
    sweep's report is written."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'lanes.db'}")
    path = sweeps / "campaigns" / "c.toml"
    path.write_text('sweeps = ["domains/one.toml", "domains/two.toml"]\n')
    campaign = load_campaign(path, sweeps)
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", reports_root=tmp_path / "reports")
    said: list[str] = []
    results = run_campaign(campaign, "smoke", echo=said.append, sweeps_dir=sweeps, parallel=2, **roots)
    assert [r.sweep for r in results] == ["domain-one", "domain-two"]
    assert [o.status for r in results for o in r.outcomes] == ["FINISHED", "FINISHED"], said
    assert sum("making its datasets in a lane" in line for line in said) == 1, said
    assert "  waits for the datasets a lane is making" in said
    # the second sweep's run went into a lane while the first's was still in its own
    into = [i for i, line in enumerate(said) if "(domain-two) into a lane" in line]
    ended = [i for i, line in enumerate(said) if "(domain-one): FINISHED" in line]
    assert len(into) == len(ended) == 1 and into[0] < ended[0], said
    for r in results:
        log = tmp_path / "runs" / r.sweep / "smoke" / r.outcomes[0].name / "progress.log"
        assert "train" in log.read_text() and "step/s" in log.read_text()
        assert (tmp_path / "reports" / r.sweep / "smoke" / "README.md").is_file()


def test_a_sweep_s_finished_runs_reach_its_run_summary_before_the_sweep_ends(sweeps: Path, tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """A campaign stopped in the middle of a sweep, on a machine that then loses its MLflow store and
    checkpoints, trains again only the runs that had not finished: each finished run reached the committed run
    summary as it ended."""
    from gns_bench.sweep import runner
    from gns_bench.sweep.runner import SUMMARISED, prepare
    from gns_bench.sweep.summaries import read_run_summary, summary_path

    (sweeps / "ablations" / "steps.toml").write_text(
        'description = "steps"\ndomain = "tiny"\n[grid]\n"model.message_passing_steps" = [1, 2]\n'
        '[tiers.smoke.config.model]\nlatent_size = 8\nmlp_hidden_size = 8\n')
    path = sweeps / "campaigns" / "c.toml"
    path.write_text('sweeps = ["ablations/steps.toml"]\n')
    campaign = load_campaign(path, sweeps)
    real, trained = runner.execute_run, []

    def stopped_at_the_second(run, *args, **kwargs):
        if trained:
            raise KeyboardInterrupt  # the session ended while the second run trained
        trained.append(run.name)
        return real(run, *args, **kwargs)

    monkeypatch.setattr(runner, "execute_run", stopped_at_the_second)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'lost.db'}")
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", reports_root=tmp_path / "reports")
    said: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        run_campaign(campaign, "smoke", progress=False, echo=said.append, sweeps_dir=sweeps, **roots)
    assert len(trained) == 1
    summary = read_run_summary(summary_path(tmp_path / "reports", "ablation-steps", "smoke"))
    assert list(summary) == trained and summary[trained[0]].status == "FINISHED"
    assert any(line.startswith("  report so far: ") for line in said)

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'new.db'}")  # a new machine: nothing kept
    shutil.rmtree(tmp_path / "runs")
    sweep = load_sweep(campaign.sweeps[0], sweeps)
    runs, status, _ = prepare(sweep, "smoke", tmp_path / "data", generate=False, reports_root=tmp_path / "reports")
    assert status[trained[0]] == SUMMARISED
    assert [r.name for r in runs if status[r.name] == "to run"] == [r.name for r in runs if r.name != trained[0]]


def test_the_front_page_counts_the_models_a_stress_sweep_would_train_again(sweeps: Path, tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """A stress sweep tests its domain run's checkpoint, and trains the model again where that checkpoint was
    lost with its store; the front page's "to go" says so beside its count, and drops it once the stress sweep
    has run."""
    from gns_bench.report.index import campaign_section

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'stress.db'}")
    (sweeps / "stress").mkdir()
    (sweeps / "stress" / "one.toml").write_text(SWEEP.format(name="tests of 'one'", steps=1)
                                                + '\n[config.stress]\ntests = ["precision"]\n')
    first = sweeps / "campaigns" / "domains.toml"
    first.write_text('sweeps = ["domains/one.toml"]\n')
    whole = sweeps / "campaigns" / "whole.toml"
    whole.write_text('sweeps = ["domains/one.toml", "stress/one.toml"]\n')
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", reports_root=tmp_path / "reports")
    run_campaign(load_campaign(first, sweeps), "smoke", progress=False, echo=lambda _: None, sweeps_dir=sweeps,
                 **roots)
    row = campaign_section(tmp_path / "reports", whole, sweeps, tiers=("smoke",))[-2]
    # one model planned (the stress sweep tests the domain's), trained; the stress sweep is still to run
    assert row.startswith("| smoke | 1 of 1 |"), row
    assert "| none; and 1 trained model again (about " in row and "if its checkpoint is gone" in row, row

    said: list[str] = []
    run_campaign(load_campaign(whole, sweeps), "smoke", progress=False, echo=said.append, sweeps_dir=sweeps, **roots)
    assert any("stress tests of domain-one" in line for line in said), said  # the checkpoint was here: tested
    row = campaign_section(tmp_path / "reports", whole, sweeps, tiers=("smoke",))[-2]
    assert row.startswith("| smoke | 1 of 1 |") and "| none |" in row, row


def test_a_campaign_dry_run_shows_a_branch_waiting_for_its_trunk(sweeps: Path, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """`gns-bench campaign --dry-run` plans with the runs root the campaign would use: a branch whose trunk's
    checkpoint is not there yet shows as waiting, not "to run", and as "to run" once it is."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    (sweeps / "studies").mkdir()
    (sweeps / "studies" / "branches.toml").write_text(
        SWEEP.format(name="a trunk and a branch of it", steps=1)
        + '\n[candidates.trunk]\n\n[candidates.branch.config.train]\n'
        'init_from = "runs:study-branches/smoke/candidate=trunk-seed{seed}/checkpoint-10.pt"\n')
    path = sweeps / "campaigns" / "c.toml"
    path.write_text('sweeps = ["studies/branches.toml"]\n')
    ensure_dataset("tiny", "smoke", 0, tmp_path / "data", progress=False)

    def plan() -> dict[str, str]:
        said: list[str] = []
        plan_campaign(load_campaign(path, sweeps), "smoke", tmp_path / "data", echo=said.append, reports_root=None,
                      runs_root=tmp_path / "runs")
        rows = [line for text in said for line in text.splitlines() if "candidate=" in line]
        return {row.split()[1]: row for row in rows}

    before = plan()
    assert "waits for the checkpoint it starts from:" in before["candidate=branch-seed0"], before
    assert "to run" in before["candidate=trunk-seed0"]
    trunk = tmp_path / "runs" / "study-branches" / "smoke" / "candidate=trunk-seed0" / "checkpoint-10.pt"
    trunk.parent.mkdir(parents=True)
    trunk.write_bytes(b"")
    assert "to run" in plan()["candidate=branch-seed0"]


def test_a_campaign_in_lanes_starts_a_branch_once_its_trunk_has_finished(sweeps: Path, tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A branch from a run's own checkpoint, planned while that run is still to train, is held and runs in the
    same campaign once the run has finished; a branch whose checkpoint nothing in the campaign writes ends
    WAITING, and the campaign ends."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'branches.db'}")
    (sweeps / "studies").mkdir()
    (sweeps / "studies" / "branches.toml").write_text(
        SWEEP.format(name="a trunk and branches of it", steps=1)
        + '\n[candidates.trunk]\n\n[candidates.branch.config.train]\nsteps = 24\n'
        'init_from = "runs:study-branches/smoke/candidate=trunk-seed{seed}/checkpoint.pt"\n'
        '\n[candidates.orphan.config.train]\nsteps = 24\n'
        'init_from = "runs:study-elsewhere/smoke/candidate=trunk-seed{seed}/checkpoint.pt"\n')
    path = sweeps / "campaigns" / "c.toml"
    path.write_text('sweeps = ["studies/branches.toml"]\n')
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", reports_root=tmp_path / "reports")
    said: list[str] = []
    [result] = run_campaign(load_campaign(path, sweeps), "smoke", echo=said.append, sweeps_dir=sweeps, parallel=2,
                            **roots)
    status = {o.name: o.status for o in result.outcomes}
    assert status == {"candidate=trunk-seed0": "FINISHED", "candidate=branch-seed0": "FINISHED",
                      "candidate=orphan-seed0": "WAITING"}, said
    trunk_done = next(i for i, line in enumerate(said) if "trunk-seed0 (study-branches): FINISHED" in line)
    branch_in = next(i for i, line in enumerate(said) if "branch-seed0 (study-branches) into a lane" in line)
    assert trunk_done < branch_in, said
    branch = tmp_path / "runs" / "study-branches" / "smoke" / "candidate=branch-seed0" / "checkpoint.pt"
    assert load_checkpoint(branch)["step"] == 24


def test_a_branch_on_a_runs_own_checkpoint_waits_until_that_run_has_finished(tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """checkpoint.pt is rewritten as its run trains: a branch from it waits until the run is FINISHED (not
    while it trains or after it stopped part-way); a kept checkpoint-<step>.pt is final once it is there."""
    from gns_bench.sweep import runner

    folder = tmp_path / "candidate=trunk-seed0"
    folder.mkdir()
    live, kept = folder / "checkpoint.pt", folder / "checkpoint-10.pt"
    assert not runner.trunk_ready(live)  # nothing there yet
    live.write_bytes(b"")
    kept.write_bytes(b"")
    assert runner.trunk_ready(live)  # no run writes it (a checkpoint brought from elsewhere)
    (folder / "mlflow_run_id").write_text("abc\n")
    status = {"abc": "RUNNING"}
    monkeypatch.setattr(runner.tracking, "get_run",
                        lambda run_id: type("Record", (), {"status": status[run_id]})())
    assert not runner.trunk_ready(live) and runner.trunk_ready(kept)
    status["abc"] = "KILLED"
    assert not runner.trunk_ready(live)
    status["abc"] = "FINISHED"
    assert runner.trunk_ready(live)


def test_a_sweep_whose_data_a_lane_made_runs_before_later_sweeps_queued_runs(sweeps: Path, tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The campaign's order holds across a dataset made in a lane: while a lane makes the first sweep's data,
    the second sweep's runs start in the other; once the data is there, the first sweep's run takes the next
    free lane, ahead of the second sweep's runs still queued."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'order.db'}")
    (sweeps / "domains" / "one.toml").write_text("dataset_seed = 1\n" + SWEEP.format(name="first", steps=1))
    (sweeps / "domains" / "two.toml").write_text(
        SWEEP.format(name="second", steps=2) + "\n[tiers.smoke]\nseeds = [0, 1, 2, 3, 4, 5]\n")
    ensure_dataset("tiny", "smoke", 0, tmp_path / "data", progress=False)  # the second sweep's; the first's is made
    path = sweeps / "campaigns" / "c.toml"
    path.write_text('sweeps = ["domains/one.toml", "domains/two.toml"]\n')
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", reports_root=tmp_path / "reports")
    said: list[str] = []
    results = run_campaign(load_campaign(path, sweeps), "smoke", echo=said.append, sweeps_dir=sweeps, parallel=2,
                           **roots)
    assert [o.status for r in results for o in r.outcomes] == ["FINISHED"] * 7, said
    lanes = [line for line in said if "into a lane" in line]
    first = next(i for i, line in enumerate(lanes) if "(domain-one)" in line)
    assert "(domain-two)" in lanes[0], said  # no lane idled while the data was made
    assert any("(domain-two)" in line for line in lanes[first + 1:]), said  # and the order held once it was
