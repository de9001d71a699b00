"""Sweeps: spec validation, a 2x2 smoke sweep end to end in MLflow, skipping, reruns, Ctrl-C, submitit."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import mlflow
import pytest
from mlflow.tracking import MlflowClient

from gns_bench import tracking
from gns_bench.cli import main
from gns_bench.config import resolve_for_dataset
from gns_bench.devices import usable_core_ids
from gns_bench.sweep.launchers import core_slices
from gns_bench.sweep.runner import prepare, run_key, run_sweep
from gns_bench.sweep.spec import SWEEPS_DIR, SweepError, discover_sweeps, load_sweep

GRID = '''description = "2x2 test grid"
domain = "tiny"

[config.train]
learning_rate = 1e-3

[tiers.smoke.config.model]
latent_size = 8
mlp_hidden_size = 8

[grid]
"model.message_passing_steps" = [1, 2]
"train.noise_std" = [0.0, 3e-4]
'''


@pytest.fixture
def sweeps(tmp_path: Path) -> Path:
    root = tmp_path / "sweeps"
    (root / "tests").mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", root / "tiers.toml")
    return root


def runs_of(experiment: str) -> list:
    tracking.configure()
    return mlflow.search_runs(experiment_names=[experiment], output_format="list")


def test_every_sweep_file_loads_and_plans() -> None:
    files = discover_sweeps()
    names = {load_sweep(p).name for p in files}
    assert {f"domain-{d}" for d in ("waterdrop", "sand-3d", "boxbath", "continuous")} <= names
    assert len([n for n in names if n.startswith("domain-")]) == 16
    ablations = {n.removeprefix("ablation-") for n in names if n.startswith("ablation-")}
    assert ablations == {"message_passing_steps", "connectivity_radius", "noise_std", "processor_sharing",
                         "position_encoding", "noise_correction", "mlp_depth", "latent_size", "self_edges",
                         "global_latent", "gravity_bias", "linear_encoder_decoder"}
    assert {n for n in names if n.startswith("study-")} == {"study-learning_rate_decay", "study-aggregate",
                                                             "study-cpu_budget", "study-gravity_curve",
                                                             "study-gravity_curve_water", "study-goop_curve",
                                                             "study-goop_candidates", "study-goop_branches",
                                                             "study-held_windows_waterdrop", "study-goop_floor",
                                                             "study-goop_curve_recipe"}
    assert {load_sweep(p).kind for p in files} == {"domain", "ablation", "stress", "study", "baseline"}
    assert load_sweep(SWEEPS_DIR / "studies" / "aggregate.toml").kind == "study"
    mp = load_sweep(SWEEPS_DIR / "ablations" / "message_passing_steps.toml")
    assert [r.config.model.message_passing_steps for r in mp.plan("small")] == [0, 1, 2, 3, 5, 7, 10, 15]
    assert all(r.config.train.steps == 20 and r.config.model.latent_size == 16 for r in mp.plan("smoke"))
    assert len(mp.plan("paper")) == 8 * 3 and mp.plan("paper")[0].config.train.steps == 20_000_000


def test_smoke_sweep_end_to_end_skip_and_rerun(sweeps: Path, tmp_path: Path) -> None:
    path = sweeps / "tests" / "grid.toml"
    path.write_text(GRID)
    sweep = load_sweep(path)
    assert sweep.name == "test-grid"
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False)

    outcomes = run_sweep(sweep, "smoke", **roots)
    assert sorted(o.status for o in outcomes) == ["FINISHED"] * 4
    runs = runs_of(sweep.experiment)
    assert len(runs) == 4 and all(r.info.status == "FINISHED" for r in runs)
    combos = {(r.data.params["model.message_passing_steps"], r.data.params["train.noise_std"]) for r in runs}
    assert combos == {("1", "0.0"), ("1", "0.0003"), ("2", "0.0"), ("2", "0.0003")}
    for r in runs:
        assert r.data.params["model.latent_size"] == "8" and r.data.params["train.steps"] == "20"
        assert r.data.params["train.learning_rate"] == "0.001"
        assert r.data.tags["axes"] == "model.message_passing_steps,train.noise_std"
        assert {"test/rollout_mse", "test/one_step_mse", "train_loss"} <= set(r.data.metrics)

    again = run_sweep(sweep, "smoke", **roots)
    assert [o.status for o in again] == ["SKIPPED"] * 4
    assert len(runs_of(sweep.experiment)) == 4

    victim = runs[0]
    MlflowClient(tracking_uri=tracking.tracking_uri()).delete_run(victim.info.run_id)
    third = run_sweep(sweep, "smoke", **roots)
    assert sorted(o.status for o in third) == ["FINISHED", "SKIPPED", "SKIPPED", "SKIPPED"]
    assert [o.name for o in third if o.status == "FINISHED"] == [victim.info.run_name]
    assert len(runs_of(sweep.experiment)) == 4


def test_a_run_another_sweep_trained_is_shared_not_retrained(sweeps: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """An ablation's default point is the domain sweep's run: same config, same data, same key."""
    own = GRID.replace("learning_rate = 1e-3", "learning_rate = 2e-3\neval_every = 10\neval_trajectories = 1\n"
                       "eval_rollout_steps = 5")  # keys no other test trains; a curve at steps 0, 10 and 20
    base_path, abl_path = sweeps / "tests" / "base.toml", sweeps / "tests" / "abl.toml"
    base_path.write_text(own.replace('"train.noise_std" = [0.0, 3e-4]\n', "").replace("[1, 2]", "[3]"))
    abl_path.write_text(own.replace('"model.message_passing_steps" = [1, 2]\n', "")
                        .replace("mlp_hidden_size = 8\n", "mlp_hidden_size = 8\nmessage_passing_steps = 3\n"))
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False)
    (source,) = run_sweep(load_sweep(base_path), "smoke", **roots)
    assert source.status == "FINISHED"

    abl = load_sweep(abl_path)
    _, status, _ = prepare(abl, "smoke", roots["data_root"])
    assert status == {"noise_std=0.0-seed0": "to run",
                      "noise_std=0.0003-seed0": "shared with test-base/message_passing_steps=3-seed0"}
    outcomes = {o.name: o for o in run_sweep(abl, "smoke", **roots)}
    assert {n: o.status for n, o in outcomes.items()} == {"noise_std=0.0-seed0": "FINISHED",
                                                          "noise_std=0.0003-seed0": "SHARED"}
    copy = next(r for r in runs_of(abl.experiment) if r.info.run_name == "noise_std=0.0003-seed0")
    trained = mlflow.get_run(source.run_id)
    assert copy.info.status == "FINISHED" and copy.info.run_id != source.run_id
    assert copy.data.tags["shared_from"] == source.run_id
    assert copy.data.tags["sweep"] == "test-abl" and copy.data.tags["axes"] == "train.noise_std"
    assert copy.data.params["sweep.name"] == "test-abl" and copy.data.params["model.message_passing_steps"] == "3"
    assert copy.data.metrics["test/rollout_mse"] == trained.data.metrics["test/rollout_mse"]
    client = mlflow.tracking.MlflowClient()
    curve = [(m.step, m.value) for m in client.get_metric_history(source.run_id, "curve/rollout_mse")]
    assert [step for step, _ in curve] == [0, 10, 20]  # the copy carries the curve at its training steps
    assert [(m.step, m.value) for m in client.get_metric_history(copy.info.run_id, "curve/rollout_mse")] == curve
    assert not (roots["runs_root"] / "test-abl" / "smoke" / "noise_std=0.0003-seed0").exists()  # nothing trained
    assert [o.status for o in run_sweep(abl, "smoke", **roots)] == ["SKIPPED", "SKIPPED"]

    unshared = sweeps / "tests" / "unshared.toml"
    unshared.write_text(abl_path.read_text())
    assert [o.status for o in run_sweep(load_sweep(unshared), "smoke", share=False, **roots)] == ["FINISHED"] * 2

    # A copy that fails half-way ends FAILED, so it never passes for the run; the next attempt copies again.
    from mlflow.tracking import MlflowClient as Client

    def store_down(*args, **kwargs):
        raise RuntimeError("store went away")

    failing = sweeps / "tests" / "failing_copy.toml"
    failing.write_text(abl_path.read_text())
    monkeypatch.setattr(Client, "log_batch", store_down)
    with pytest.raises(RuntimeError, match="store went away"):
        run_sweep(load_sweep(failing), "smoke", **roots)
    monkeypatch.undo()
    (half,) = runs_of("sweep:test-failing_copy")
    assert half.info.status == "FAILED" and "store went away" in half.data.tags["error"]
    again = {o.name: o.status for o in run_sweep(load_sweep(failing), "smoke", **roots)}
    assert again == {"noise_std=0.0-seed0": "SHARED", "noise_std=0.0003-seed0": "SHARED"}


def test_only_and_no_train_choose_what_a_session_runs(sweeps: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    """A session with an hour trains one chosen point; `--no-train` records shared runs and trains none."""
    own = GRID.replace("learning_rate = 1e-3", "learning_rate = 3e-3")  # keys no other test trains
    base_path, abl_path = sweeps / "tests" / "obase.toml", sweeps / "tests" / "oabl.toml"
    base_path.write_text(own.replace('"train.noise_std" = [0.0, 3e-4]\n', "").replace("[1, 2]", "[2]"))
    abl_path.write_text(own)
    roots = ["--data-root", str(tmp_path / "data"), "--runs-root", str(tmp_path / "runs"),
             "--reports-root", str(tmp_path / "reports")]
    abl = load_sweep(abl_path)
    assert main(["sweep", str(abl_path), "--only", "nothing-*", *roots]) == 2
    assert "no run matches --only nothing-*" in capsys.readouterr().err
    assert runs_of(abl.experiment) == []

    assert main(["sweep", str(abl_path), "--only", "message_passing_steps=1,noise_std=0.0-*", *roots]) == 0
    assert [r.info.run_name for r in runs_of(abl.experiment)] == ["message_passing_steps=1,noise_std=0.0-seed0"]

    assert main(["sweep", str(base_path), *roots]) == 0
    assert main(["sweep", str(abl_path), "--no-train", *roots]) == 0
    assert "2 to run, not trained" in capsys.readouterr().out
    statuses = {r.info.run_name: ("shared_from" in r.data.tags) for r in runs_of(abl.experiment)}
    assert statuses == {"message_passing_steps=1,noise_std=0.0-seed0": False,
                        "message_passing_steps=2,noise_std=0.0003-seed0": True}
    _, status, _ = prepare(abl, "smoke", tmp_path / "data", only=["*noise_std=0.0-*"])
    assert status == {"message_passing_steps=1,noise_std=0.0-seed0": "finished",
                      "message_passing_steps=2,noise_std=0.0-seed0": "to run"}


def test_dry_run_prints_the_table(sweeps: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = sweeps / "tests" / "dry.toml"
    path.write_text(GRID)
    assert main(["sweep", str(path), "--dry-run", "--data-root", str(tmp_path / "data")]) == 0
    out = capsys.readouterr().out
    assert "4 runs" in out and "message_passing_steps" in out and "dataset missing" in out
    assert mlflow.get_experiment_by_name("sweep:test-dry") is None


@pytest.mark.parametrize(
    "text, message",
    [(GRID.replace("domain =", "domian ="), "unknown key 'domian'"),
     (GRID.replace("latent_size = 8", "latent_size = \"big\""), "model.latent_size: expected int"),
     (GRID.replace("learning_rate = 1e-3", "learning_rate = -1.0"), "train.learning_rate: must be > 0"),
     (GRID.replace('"train.noise_std" = [0.0, 3e-4]', '"train.noise_std" = [-1.0]'), "must be >= 0"),
     (GRID.replace('"train.noise_std"', '"train.noise"'), "unknown key 'train.noise'"),
     (GRID + "\n[tiers.huge]\nseeds = [0]\n", "unknown tier 'tiers.huge'"),
     (GRID + "\n[tiers.smoke]\nseeds = []\n", "tiers.smoke.seeds"),
     (GRID + "\n[tiers.smoke]\ngrid = { \"model.latent_size\" = [4] }\n", "does not have")],
)
def test_broken_sweep_file_gives_a_clear_error_and_runs_nothing(sweeps: Path, tmp_path: Path, text: str,
                                                                 message: str, capsys: pytest.CaptureFixture) -> None:
    path = sweeps / "tests" / "broken.toml"
    path.write_text(text)
    with pytest.raises(SweepError, match=message):
        load_sweep(path)
    assert main(["sweep", str(path), "--data-root", str(tmp_path / "data")]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and not (tmp_path / "data").exists()
    assert mlflow.get_experiment_by_name("sweep:test-broken") is None


def interrupted_at_step_7(monkeypatch: pytest.MonkeyPatch, run: Callable[[], object]) -> None:
    """`run()` with Ctrl-C pressed during the 7th training step (the training loss raises it), then the loss
    restored."""
    from gns_bench.train import losses  # where the GNS's training loss lives (its registry entry calls it)

    real, calls = losses.training_loss, {"n": 0}

    def interrupt_at_step_7(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 7:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(losses, "training_loss", interrupt_at_step_7)
    with pytest.raises(KeyboardInterrupt):
        run()
    monkeypatch.setattr(losses, "training_loss", real)



def test_a_report_shows_an_unfinished_attempt_only_under_the_plan_it_trained(sweeps: Path, tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """A candidate whose recipe changes keeps its name; its killed attempt at the earlier recipe is another model
    and no longer shows in the report's row for that name (`report/collect.py`)."""
    from gns_bench.report.collect import collect

    path = sweeps / "tests" / "changed.toml"
    one_run = GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', "")
    path.write_text(one_run.replace('"model.message_passing_steps" = [1, 2]', '"model.message_passing_steps" = [1]'))
    sweep = load_sweep(path)
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, share=False)
    interrupted_at_step_7(monkeypatch, lambda: run_sweep(sweep, "smoke", **roots))
    (row,) = collect(sweep, "smoke", tmp_path / "reports")
    assert row.record is not None and row.record.status == "KILLED"  # the attempt shows under its own plan
    path.write_text(path.read_text().replace("learning_rate = 1e-3", "learning_rate = 2e-3"))
    (row,) = collect(load_sweep(path), "smoke", tmp_path / "reports")
    assert row.record is None  # the same name, another recipe: missing, not the old attempt

def test_ctrl_c_leaves_no_finished_run_and_resumes(sweeps: Path, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    path = sweeps / "tests" / "interrupt.toml"
    path.write_text(GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', ""))
    sweep = load_sweep(path)
    # share=False: the end-to-end test trained these configs already; this test is about training them
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, share=False)
    interrupted_at_step_7(monkeypatch, lambda: run_sweep(sweep, "smoke", **roots))
    (killed,) = runs_of(sweep.experiment)
    assert killed.info.status == "KILLED"
    outcomes = run_sweep(sweep, "smoke", **roots)
    assert sorted(o.status for o in outcomes) == ["FINISHED", "FINISHED"]
    runs = runs_of(sweep.experiment)
    assert len(runs) == 2 and all(r.info.status == "FINISHED" for r in runs)
    resumed = next(r for r in runs if r.info.run_id == killed.info.run_id)
    assert "error" not in resumed.data.tags and "KeyboardInterrupt" in resumed.data.tags["resumed_after"]
    steps = [m.step for m in MlflowClient(tracking_uri=tracking.tracking_uri()).get_metric_history(
        resumed.info.run_id, "train_loss")]
    assert steps == [10, 20]  # steps 1-6 kept from the checkpoint, the rest resumed in the same run


def test_a_run_whose_plan_changed_starts_afresh(sweeps: Path, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """A stopped run is resumed only under the same key: once its tier's budget changes it is another run."""
    path = sweeps / "tests" / "replanned.toml"
    text = GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', "").replace("[1, 2]", "[1]")
    path.write_text(text)
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, share=False)
    from gns_bench.train import losses as loop

    real = loop.training_loss

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(loop, "training_loss", interrupt)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(load_sweep(path), "smoke", **roots)
    monkeypatch.setattr(loop, "training_loss", real)
    (killed,) = runs_of("sweep:test-replanned")
    path.write_text(text.replace("learning_rate = 1e-3", "learning_rate = 1e-3\nlearning_rate_decay_steps = 1e3"))
    (outcome,) = run_sweep(load_sweep(path), "smoke", **roots)  # resuming would fail: train settings differ
    assert outcome.status == "FINISHED" and outcome.run_id != killed.info.run_id, outcome.error
    statuses = {r.info.run_id: r.info.status for r in runs_of("sweep:test-replanned")}
    assert statuses == {killed.info.run_id: "KILLED", outcome.run_id: "FINISHED"}
    # the earlier attempt's folder, checkpoint included, is set aside, not deleted
    (aside,) = (tmp_path / "runs").rglob("*.set-aside-1")
    assert (aside / "checkpoint.pt").is_file() and (aside / "mlflow_run_id").read_text().strip() == killed.info.run_id


def test_a_run_killed_before_its_first_checkpoint_starts_afresh_and_ends_its_record(
        sweeps: Path, tmp_path: Path) -> None:
    """A process killed outright (SIGKILL, a lost machine) leaves its MLflow run RUNNING and no checkpoint: the
    next attempt sets the folder aside, ends that record KILLED with the reason, and trains a new run."""
    path = sweeps / "tests" / "killed.toml"
    path.write_text(GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', "").replace("[1, 2]", "[1]"))
    sweep = load_sweep(path)
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, share=False)
    (planned,), _, _ = prepare(sweep, "smoke", data_root=roots["data_root"], progress=False, share=False)
    out_dir = roots["runs_root"] / planned.sweep / planned.tier / planned.name
    out_dir.mkdir(parents=True)
    tracking.configure()
    client = MlflowClient()
    orphan = client.create_run(tracking.experiment_id(sweep.experiment), run_name=planned.name).info.run_id
    (out_dir / "mlflow_run_id").write_text(orphan)  # what a killed attempt leaves behind: no checkpoint.pt
    (outcome,) = run_sweep(sweep, "smoke", **roots)
    assert outcome.status == "FINISHED" and outcome.run_id != orphan, outcome.error
    ended = client.get_run(orphan)
    assert ended.info.status == "KILLED" and ended.info.end_time is not None
    assert "set aside" in ended.data.tags["error"] and ended.data.tags["error"].endswith("set-aside-1")
    assert (out_dir.with_name(f"{out_dir.name}.set-aside-1") / "mlflow_run_id").read_text() == orphan


def test_submitit_local_executor(sweeps: Path, tmp_path: Path) -> None:
    path = sweeps / "tests" / "submitit.toml"
    path.write_text(GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', ""))
    sweep = load_sweep(path)
    outcomes = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs",
                         launcher="submitit", cluster="local", progress=False, share=False)
    assert sorted(o.status for o in outcomes) == ["FINISHED", "FINISHED"], [o.error for o in outcomes]
    runs = runs_of(sweep.experiment)
    assert sorted(r.data.params["model.message_passing_steps"] for r in runs) == ["1", "2"]
    assert all(r.info.status == "FINISHED" for r in runs)


def test_core_slices_divide_the_cores_between_jobs() -> None:
    assert core_slices([0, 1, 2, 3, 4], 2) == [[0, 1, 2], [3, 4]]
    assert core_slices([4, 5], 2) == [[4], [5]]
    assert core_slices([0, 1], 3) == [[0], [1], [0]]  # more jobs than cores: one each, shared in turn
    with pytest.raises(ValueError, match="at least 1"):
        core_slices([0, 1], 0)


def test_parallel_runs_each_in_its_own_process_on_its_own_cores(sweeps: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture) -> None:
    path = sweeps / "tests" / "parallel.toml"
    path.write_text(GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', ""))
    sweep = load_sweep(path)
    outcomes = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs",
                         progress=False, share=False, parallel=2)
    assert [o.status for o in outcomes] == ["FINISHED", "FINISHED"], [o.error for o in outcomes]
    assert "[2/2]" in capsys.readouterr().out  # each run's end is told as it comes
    runs = runs_of(sweep.experiment)
    assert sorted(r.data.params["model.message_passing_steps"] for r in runs) == ["1", "2"]
    threads = [int(r.data.tags["hardware"].rsplit(", ", 1)[1].split()[0]) for r in runs]
    cores = len(usable_core_ids())
    assert sum(threads) <= max(cores, 2), (threads, cores)  # the cores divided, not each run taking them all
    with pytest.raises(ValueError, match="local launcher"):
        run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", launcher="submitit",
                  parallel=2)


def test_nox_has_one_session_per_sweep_file(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util

    import nox.registry

    monkeypatch.chdir(SWEEPS_DIR.parent)
    spec = importlib.util.spec_from_file_location("noxfile_under_test", SWEEPS_DIR.parent / "noxfile.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sessions = set(nox.registry.get())
    assert {load_sweep(p).name for p in discover_sweeps()} <= sessions
    assert {"tests", "lint", "ui"} <= sessions


def test_a_failing_run_is_recorded_failed_and_the_sweep_goes_on(sweeps: Path, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    path = sweeps / "tests" / "failing.toml"
    path.write_text(GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', ""))
    sweep = load_sweep(path)
    from gns_bench.train import losses as loop

    real = loop.training_loss

    def broken_for_m2(simulator, *args, **kwargs):
        if simulator.config.message_passing_steps == 2:
            raise RuntimeError("diverged on purpose")
        return real(simulator, *args, **kwargs)

    monkeypatch.setattr(loop, "training_loss", broken_for_m2)
    outcomes = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False,
                         share=False)
    assert sorted(o.status for o in outcomes) == ["FAILED", "FINISHED"]
    failed = next(o for o in outcomes if o.status == "FAILED")
    assert "diverged on purpose" in failed.error and failed.run_id
    runs = {r.info.run_name: r for r in runs_of(sweep.experiment)}
    assert runs[failed.name].info.status == "FAILED"
    assert "diverged on purpose" in runs[failed.name].data.tags["error"]


def dataset_key(run, dataset_hash: str, radius: float = 0.015) -> str:
    """The key `dataset_run_key` gives `run` on a dataset with this hash and default radius."""
    return run_key(resolve_for_dataset(run.config, radius), run.domain, dataset_hash)


def test_run_key_ignores_fields_at_their_default(monkeypatch: pytest.MonkeyPatch) -> None:
    """A config field added later with a default must not change the keys of runs already done."""
    import dataclasses

    from gns_bench.config import Config

    run = next(iter(load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml").plan("smoke")))
    key = dataset_key(run, "abc")
    assert dataset_key(run, "abd") != key  # the dataset is in the key
    changed = dataclasses.replace(run, config=dataclasses.replace(
        run.config, train=dataclasses.replace(run.config.train, compile=not run.config.train.compile)))
    assert dataset_key(changed, "abc") != key  # a non-default value is in the key
    without = Config.to_dict

    def older_config(self: Config) -> dict:  # as if `train.compile` did not exist yet
        values = without(self)
        del values["train"]["compile"]
        return values

    monkeypatch.setattr(Config, "to_dict", older_config)
    assert dataset_key(run, "abc") == key

    def with_a_new_section(self: Config) -> dict:  # a section added later, at its defaults
        return {**without(self), "newer": {"knob": 1}}

    monkeypatch.setattr(Config, "to_dict", with_a_new_section)
    assert dataset_key(run, "abc") == key


def test_run_key_resolves_a_radius_equal_to_the_datasets() -> None:
    """The radius ablation's point at the dataset's default R is the domain run, which leaves R unset: both
    resolve to the same number against the dataset."""
    import dataclasses

    plan = {r.name: r for r in load_sweep(SWEEPS_DIR / "ablations" / "connectivity_radius.toml").plan("small")}
    domain_run = next(iter(load_sweep(SWEEPS_DIR / "domains" / "goop.toml").plan("small")))
    at_default, wider = plan["connectivity_radius=0.015-seed0"], plan["connectivity_radius=0.02-seed0"]
    unset = dataclasses.replace(at_default, config=dataclasses.replace(
        at_default.config, model=dataclasses.replace(at_default.config.model, connectivity_radius=None)))
    assert dataset_key(at_default, "abc") == dataset_key(unset, "abc") == dataset_key(domain_run, "abc")
    assert dataset_key(wider, "abc") != dataset_key(domain_run, "abc")
    assert dataset_key(at_default, "abc", 0.02) != dataset_key(domain_run, "abc", 0.02)  # another dataset's R


def test_experiment_created_by_a_parallel_run_is_reused(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two runs of a sweep starting at once (submitit, torchrun) may both find no experiment and both create
    it; the one that loses the race must use the other's, not fail."""
    first = tracking.experiment_id("race")
    lookup = mlflow.get_experiment_by_name
    calls = []

    def not_yet_there(name: str):  # the check happens just before the other process creates it
        calls.append(name)
        return None if len(calls) == 1 else lookup(name)

    monkeypatch.setattr(mlflow, "get_experiment_by_name", not_yet_there)
    assert tracking.experiment_id("race") == first
    assert len(calls) == 2


def test_reevaluate_replaces_the_evaluation_and_copies_afresh(sweeps: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture) -> None:
    """`--reevaluate` evaluates a finished run again into its own MLflow run (the old values stay in the
    metric history), drops the evaluation tags and artifacts it no longer earns, and re-copies shared runs."""
    own = GRID.replace("learning_rate = 1e-3", "learning_rate = 4e-3")  # keys no other test trains
    own = own.replace("[grid]", "[config.eval]\nmonitors = false\n\n[grid]")  # no monitor can stop this one
    base_path, abl_path = sweeps / "tests" / "rbase.toml", sweeps / "tests" / "rabl.toml"
    base_path.write_text(own.replace('"train.noise_std" = [0.0, 3e-4]\n', "").replace("[1, 2]", "[1]"))
    abl_path.write_text(own.replace('"model.message_passing_steps" = [1, 2]\n', "")
                        .replace("mlp_hidden_size = 8\n", "mlp_hidden_size = 8\nmessage_passing_steps = 1\n")
                        .replace("[0.0, 3e-4]", "[3e-4]"))
    roots = ["--data-root", str(tmp_path / "data"), "--runs-root", str(tmp_path / "runs"),
             "--reports-root", str(tmp_path / "reports")]
    assert main(["sweep", str(base_path), *roots]) == 0
    assert main(["sweep", str(abl_path), *roots]) == 0
    (source,) = runs_of("sweep:test-rbase")
    (old_copy,) = runs_of("sweep:test-rabl")
    assert old_copy.data.tags["shared_from"] == source.info.run_id

    # What an earlier evaluation left that this one will not earn: a stop tag and the stopped states
    client = MlflowClient(tracking_uri=tracking.tracking_uri())
    client.set_tag(source.info.run_id, "test/rollouts_stopped", "trajectory 0: out_of_bounds at step 3")
    stale = tmp_path / "test_monitor_states.npz"
    stale.write_bytes(b"stale")
    client.log_artifact(source.info.run_id, str(stale), "evaluation")

    assert main(["sweep", str(base_path), "--reevaluate", "a test", *roots]) == 0
    assert "1 evaluated again" in capsys.readouterr().out
    (after,) = runs_of("sweep:test-rbase")
    assert after.info.run_id == source.info.run_id and after.info.status == "FINISHED"
    assert "a test" in after.data.tags["reevaluated"]
    assert "test/rollouts_stopped" not in after.data.tags
    artifacts = {f.path for f in client.list_artifacts(source.info.run_id, "evaluation")}
    assert "evaluation/test_monitor_states.npz" not in artifacts and "evaluation/test_rollouts.npz" in artifacts
    assert len(client.get_metric_history(source.info.run_id, "test/rollout_mse")) == 2  # old value kept
    assert after.data.metrics["train/final_step"] == source.data.metrics["train/final_step"]  # not retrained

    # a checkpoint that another MLflow run left in the run's directory is not evaluated into this one
    from gns_bench.pipeline import reevaluate_run
    from gns_bench.sweep.runner import run_dir

    (planned,) = load_sweep(base_path).plan("smoke")
    out_dir = run_dir(tmp_path / "runs", planned)
    with pytest.raises(ValueError, match="belongs to MLflow run"):
        reevaluate_run("0" * 32, tmp_path / "data", out_dir, planned.config.eval, reason="wrong run")

    # The same from the command line, for a run no sweep plans any more: into the run that trained the
    # checkpoint, with that run's own evaluation settings (1 trajectory at the smoke tier, where the command's
    # plain `evaluate` would take every test trajectory)
    from gns_bench.datasets import dataset_path

    dataset = dataset_path(planned.domain, planned.dataset_tier, planned.dataset_seed, tmp_path / "data")
    assert main(["evaluate", str(out_dir), str(dataset), "--into", source.info.run_id, "--reason", "by hand"]) == 0
    again = client.get_run(source.info.run_id)
    assert "by hand" in again.data.tags["reevaluated"] and again.data.metrics["test/num_trajectories"] == 1
    assert len(client.get_metric_history(source.info.run_id, "test/rollout_mse")) == 3
    assert main(["evaluate", str(tmp_path), str(dataset), "--into", source.info.run_id]) == 2  # no config.json

    assert main(["sweep", str(abl_path), "--reevaluate", *roots]) == 0
    (new_copy,) = runs_of("sweep:test-rabl")
    assert new_copy.info.run_id != old_copy.info.run_id and new_copy.data.tags["shared_from"] == source.info.run_id
    assert client.get_run(old_copy.info.run_id).info.lifecycle_stage == "deleted"


def test_the_decay_study_shares_its_compressed_and_paper_points_with_the_goop_domain_runs() -> None:
    """The study's 5,000-step point is the GOOP small run's config (tiers.toml), and its 5,000,000-step point
    the paper's default: both must key like a domain-goop run, so they are shared, not trained again."""
    study = {r.config.train.learning_rate_decay_steps: r for r in
             load_sweep(SWEEPS_DIR / "studies" / "learning_rate_decay.toml").plan("small")}
    goop = load_sweep(SWEEPS_DIR / "domains" / "goop.toml").plan("small")[0]
    assert sorted(study) == [2_500, 5_000, 10_000, 5_000_000]
    assert dataset_key(study[5_000], "hash") == dataset_key(goop, "hash")
    paper_decay = replace(goop, config=replace(goop.config, train=replace(goop.config.train,
                                                                         learning_rate_decay_steps=5_000_000)))
    assert dataset_key(study[5_000_000], "hash") == dataset_key(paper_decay, "hash")
    assert dataset_key(study[10_000], "hash") != dataset_key(goop, "hash")


STUDY = '''description = "two candidates"
domain = "tiny"

[tiers.smoke]
eval_dataset_tier = "smoke"

[tiers.smoke.config.model]
latent_size = 8
mlp_hidden_size = 8

[tiers.smoke.config.train]
eval_every = 10
eval_trajectories = 1
eval_rollout_steps = 5

[candidates.plain]
config.model = { message_passing_steps = 1 }

[candidates.more-data]
dataset_tier = "small"
config.model = { message_passing_steps = 2 }
'''


def test_a_study_of_candidates_trains_each_on_its_data_and_tests_all_on_one(sweeps: Path, tmp_path: Path) -> None:
    """A sweep of named candidates: each its own config (and perhaps its own training data), every one
    evaluated on the same test split (the tier's eval_dataset_tier), and keyed by both datasets."""
    (sweeps / "studies").mkdir()
    path = sweeps / "studies" / "two.toml"
    path.write_text(STUDY)
    sweep = load_sweep(path)
    assert sweep.kind == "study" and sweep.axes == ["candidate"]
    runs = {r.name: r for r in sweep.plan("smoke")}
    assert sorted(runs) == ["candidate=more-data-seed0", "candidate=plain-seed0"]
    more, plain = runs["candidate=more-data-seed0"], runs["candidate=plain-seed0"]
    assert (more.dataset_tier, more.evaluated_on) == ("small", "smoke") and more.eval_dataset_tier == "smoke"
    assert (plain.dataset_tier, plain.evaluated_on, plain.eval_dataset_tier) == ("smoke", "smoke", None)
    assert more.config.model.message_passing_steps == 2 and more.config.model.latent_size == 8
    outcomes = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False,
                         reports_root=tmp_path / "reports")
    assert sorted(o.status for o in outcomes) == ["FINISHED", "FINISHED"], [o.error for o in outcomes]
    previous_uri = tracking.tracking_uri()
    logged = {r.info.run_name: r for r in runs_of(sweep.experiment)}
    trained_on = logged["candidate=more-data-seed0"].data.tags
    assert trained_on["dataset_tier"] == "small" and trained_on["eval_dataset_tier"] == "smoke"
    assert trained_on["eval_dataset_hash"] == logged["candidate=plain-seed0"].data.tags["dataset_hash"]
    from gns_bench.report import write_report

    summary = tmp_path / "reports" / "study-two" / "smoke" / "runs.json"
    recorded = summary.read_bytes()  # the runner's record of both runs, curves included
    assert all(json.loads(recorded)["runs"][i]["curves"] for i in range(2))
    text = write_report(path, "smoke", tmp_path / "reports").read_text()
    assert summary.read_bytes() == recorded  # the report reads the records; it does not write them
    assert "| `plain` | 1 | 20 |" in text and "| `more-data` | 1 | 20 |" in text  # one seed, 20 steps each
    assert "**Winner.**" not in text  # smoke: a pipeline check names no winner
    assert "![error against training time](error_vs_time.png)" in text
    assert (tmp_path / "reports" / "study-two" / "smoke" / "error_vs_time.png").stat().st_size > 5000
    where = text[text.index("## Where the curves go"):]  # each run's trend, fitted from its curve
    assert "| candidate=plain-seed0 | one-step MSE | 20 |" in where
    # a stopped rollout is counted over the whole horizon (held), in the table and the trend
    assert "| candidate=plain-seed0 | whole-rollout MSE, stops held | 20 |" in where
    plain_row = next(line for line in text.splitlines() if line.startswith("| `plain` |")).split(" | ")
    header = next(line for line in text.splitlines() if line.startswith("| candidate |")).split(" | ")
    held = plain_row[header.index("whole rollout, stops held, vs constant velocity")]
    assert held.endswith(")") and "x (" in held, held
    assert "| candidate=plain-seed0 | step 20: " in where[where.index("Whole rollouts along training"):]
    gravity = where[where.index("| run | gravity ratio within 10% of 1"):].split("\n\n")[0].splitlines()[2:]
    assert sorted(line.split(" | ")[0] for line in gravity) == ["| candidate=more-data-seed0",
                                                                 "| candidate=plain-seed0"]
    assert all(("from step " in line or "not by step 20 (last" in line) for line in gravity)
    assert all(line.count(" | ") == 3 for line in gravity)  # run, gravity on true windows and rollout, floor's push
    assert (tmp_path / "reports" / "study-two" / "smoke" / "trend.png").stat().st_size > 5000
    # the run summary the runner wrote rebuilds the same tables and curves when the MLflow store is gone
    tracking.use_tracking_uri(f"sqlite:///{tmp_path / 'empty.db'}")
    try:
        again = write_report(path, "smoke", tmp_path / "reports").read_text()
    finally:
        tracking.use_tracking_uri(previous_uri)
    table = [line for line in text.splitlines() if line.startswith("| `")]
    assert table and table == [line for line in again.splitlines() if line.startswith("| `")]
    assert "![error against training time](error_vs_time.png)" in again
    with pytest.raises(SweepError, match="not both"):
        path.write_text(STUDY + '\n[grid]\n"train.noise_std" = [0.0]\n')
        load_sweep(path)


def test_a_study_report_draws_a_run_still_training_and_is_rebuilt_without_mlflow(
        sweeps: Path, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A run still training has no place in the runner's summary (finished runs only), yet its curves so far
    are worth reading: the study's report draws them, says how far they went, and keeps the run
    (`report.json`), so that the report is rebuilt the same where MLflow no longer holds it."""
    from gns_bench.report import write_report
    from gns_bench.sweep.summaries import read_run_summary, summary_path, write_run_summary

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'first.db'}")
    (sweeps / "studies").mkdir()
    path = sweeps / "studies" / "two.toml"
    path.write_text(STUDY)
    sweep = load_sweep(path)
    reports = tmp_path / "reports"
    run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False,
              reports_root=reports)
    summary = summary_path(reports, sweep.name, "smoke")
    held = read_run_summary(summary)
    training = held.pop("candidate=plain-seed0")  # as if it were still training: not in the summary yet
    write_run_summary(summary, sweep.name, "smoke", held.values())
    MlflowClient().update_run(training.run_id, status="RUNNING")
    text = write_report(path, "smoke", reports).read_text()
    assert ("Not finished when this report was written, drawn as far as they went: candidate=plain-seed0 "
            "(running, evaluated to step 20 of 20)") in text
    assert "| candidate=plain-seed0 | plain | 0 | **running** |" in text
    kept = json.loads((reports / sweep.name / "smoke" / "report.json").read_text())["kept"]["unfinished"]
    assert list(kept) == ["candidate=plain-seed0"] and kept["candidate=plain-seed0"]["curves"]["curve/rollout_mse"]
    figure = (reports / sweep.name / "smoke" / "error_vs_time.png").read_bytes()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'empty.db'}")  # the store is gone
    assert write_report(path, "smoke", reports).read_text() == text
    assert (reports / sweep.name / "smoke" / "error_vs_time.png").read_bytes() == figure


def test_the_default_point_takes_the_tiers_default_seeds(sweeps: Path) -> None:
    """An ablation's point at the paper's default gets `default_seeds` (its seed spread is the band the
    verdicts are judged against); the other points keep the tier's seeds. A default off the grid is refused."""
    path = sweeps / "tests" / "defaults.toml"
    default = 'default = { "model.message_passing_steps" = 2, "train.noise_std" = 3e-4 }\n'
    path.write_text(default + GRID + "\n[tiers.smoke]\ndefault_seeds = [0, 1, 2]\n")
    plan = load_sweep(path).plan("smoke")
    seeds: dict[tuple, list[int]] = {}
    for run in plan:
        seeds.setdefault(tuple(run.axes.values()), []).append(run.seed)
    assert seeds[(2, 3e-4)] == [0, 1, 2] and seeds[(1, 3e-4)] == [0] and seeds[(2, 0.0)] == [0]
    path.write_text(default.replace("= 2", "= 7") + GRID)
    with pytest.raises(SweepError, match="not among the axis values"):
        load_sweep(path)


def test_a_sweep_loaded_again_reads_its_file_and_its_tiers_as_they_are_now(sweeps: Path) -> None:
    """`load_sweep` keeps what it loaded (the reports read every sweep many times), by both files' bytes."""
    path = sweeps / "tests" / "again.toml"
    path.write_text(GRID)
    first = load_sweep(path)
    assert load_sweep(path) is first  # nothing changed: parsed and planned once
    assert {r.config.train.steps for r in first.plan("smoke")} == {20}
    tiers = sweeps / "tiers.toml"
    tiers.write_text(tiers.read_text().replace("config.train = { steps = 20,", "config.train = { steps = 30,", 1))
    assert {r.config.train.steps for r in load_sweep(path).plan("smoke")} == {30}  # the tiers' file changed
    path.write_text(GRID + "\n[tiers.smoke.config.train]\nsteps = 40\n")
    assert {r.config.train.steps for r in load_sweep(path).plan("smoke")} == {40}  # the sweep's own changed


def test_a_stress_sweep_tests_the_model_a_domain_sweep_trained_instead_of_training_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")  # its runs shared with no test
    root = tmp_path / "sweeps"
    for folder in ("domains", "stress"):
        (root / folder).mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", root / "tiers.toml")
    model = "[tiers.smoke.config.model]\nlatent_size = 8\nmlp_hidden_size = 8\n"
    (root / "domains" / "tiny.toml").write_text(f'description = "the model"\ndomain = "tiny"\n\n{model}')
    (root / "stress" / "tiny.toml").write_text(
        f'description = "its stress tests"\ndomain = "tiny"\n\n[config.stress]\ntests = ["precision"]\n'
        f'precisions = ["fp32", "bf16"]\nmax_trajectories = 1\nrollout_steps = 8\n\n{model}')
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, echo=lambda line: None)
    domain, stress = load_sweep(root / "domains" / "tiny.toml", root), load_sweep(root / "stress" / "tiny.toml", root)
    [trained] = run_sweep(domain, "smoke", **roots)
    runs, status, _ = prepare(stress, "smoke", tmp_path / "data", progress=False)
    assert status[runs[0].name] == f"stress tests of domain-tiny/{runs[0].name}"
    [tested] = run_sweep(stress, "smoke", **roots)
    assert trained.status == tested.status == "FINISHED"
    record = tracking.get_run(tested.run_id)
    assert record.tags["shared_from"] == trained.run_id and record.tags["stress/tests"] == "precision"
    assert record.metrics["test/rollout_mse"] == trained.metrics["rollout_mse"]  # the same model's evaluation
    assert any(k.startswith("stress/precision/") for k in record.metrics)
    assert not any(k.startswith("stress/") for k in tracking.get_run(trained.run_id).metrics)
    checkpoint = tmp_path / "runs" / "stress-tiny" / "smoke" / runs[0].name / "checkpoint.pt"
    source = tmp_path / "runs" / "domain-tiny" / "smoke" / runs[0].name / "checkpoint.pt"
    assert checkpoint.read_bytes() == source.read_bytes()  # tested, not trained again
    assert [o.status for o in run_sweep(stress, "smoke", **roots)] == ["SKIPPED"]
    from gns_bench.report import write_report

    report = write_report(root / "stress" / "tiny.toml", "smoke", tmp_path / "reports").read_text()
    assert tested.run_id in report and "# precision" in report  # the stress results the tested copy holds
    assert "rollout_mse_bf16" in report


def test_the_cpu_stress_sweeps_test_their_domain_sweeps_models() -> None:
    """At the campaign's tier a stress sweep's runs must train exactly what its domain sweep trains (all but
    [stress]), so that the runner tests that checkpoint instead of training another model: a per-domain
    budget set in one file and not the other would break this."""
    from dataclasses import replace as replace_config

    from gns_bench.config import StressConfig

    domains = {load_sweep(p).domain: load_sweep(p) for p in discover_sweeps() if load_sweep(p).kind == "domain"}
    checked = 0
    for sweep in (load_sweep(p) for p in discover_sweeps()):
        if sweep.kind != "stress" or sweep.domain not in domains:
            continue
        [tested] = sweep.plan("cpu")
        trained = {r.seed: r for r in domains[sweep.domain].plan("cpu")}[tested.seed]
        assert tested.config.stress.enabled, sweep.name
        assert replace_config(tested.config, stress=StressConfig()) == trained.config, sweep.name
        checked += 1
    assert checked == 4  # WATERRAMPS, CONTINUOUS, MULTIMATERIAL, BOXBATH (the shaken box trains its own)


def test_every_cpu_gns_run_follows_the_budget_studys_winner() -> None:
    """The cpu tier is the budget study's winner (sweeps/tiers.toml): bf16, the paper's peak learning rate, the
    decay at 10x per half of the run whatever a domain's steps, and the rollouts tables report in fp32. A domain
    sweep that sets its own steps and forgets the decay (or a stress sweep that copies one and not the other)
    fails here. CConv and DPI-Net train on their own papers' schedules (model/cconv.py, model/dpi.py)."""
    checked = 0
    for sweep in (load_sweep(p) for p in discover_sweeps()):
        if sweep.kind == "study":
            continue
        for run in sweep.plan("cpu"):
            train = run.config.train
            if run.config.model.architecture != "gns":
                continue
            assert train.learning_rate_decay_steps * 2 == train.steps, (sweep.name, run.name)
            assert train.precision == "bf16" and train.learning_rate == 1e-4, (sweep.name, run.name)
            assert run.config.eval.precision == "fp32", (sweep.name, run.name)  # reported rollouts in fp32
            checked += 1
    assert checked > 40


def test_a_run_whose_data_was_made_again_differently_says_it_trains_again(
        sweeps: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A dataset made again (a new machine, its store and data gone) whose content hash differs from the one the
    committed summary's run trained on: the run is another run and trains again, and the plan says so first."""
    from gns_bench.sweep.runner import start_sweep

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'first.db'}")
    path = sweeps / "tests" / "one.toml"
    path.write_text(GRID.replace('"model.message_passing_steps" = [1, 2]\n"train.noise_std" = [0.0, 3e-4]\n', ""))
    sweep = load_sweep(path)
    reports, data = tmp_path / "reports", tmp_path / "data"
    [trained] = run_sweep(sweep, "smoke", data_root=data, runs_root=tmp_path / "runs", progress=False,
                          reports_root=reports, echo=lambda line: None)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'new.db'}")  # a new machine
    lines: list[str] = []
    start_sweep(sweep, "smoke", data_root=data, reports_root=reports, train=False, progress=False,
                echo=lines.append)
    assert not any("trains again" in line for line in lines)  # the same data: known finished
    path.write_text(path.read_text().replace("latent_size = 8", "latent_size = 9"))  # another plan, same data
    lines.clear()
    start_sweep(load_sweep(path), "smoke", data_root=data, reports_root=reports, train=False, progress=False,
                echo=lines.append)
    assert any("1 to run" in line for line in lines) and not any("trains again" in line for line in lines)
    [dataset] = [d for d in data.iterdir() if (d / "metadata.json").is_file()]
    meta = json.loads((dataset / "metadata.json").read_text())
    old, meta["content_hash"] = meta["content_hash"], "0" * 64
    (dataset / "metadata.json").write_text(json.dumps(meta))
    lines.clear()
    start_sweep(sweep, "smoke", data_root=data, reports_root=reports, train=False, progress=False,
                echo=lines.append)
    assert f"  {trained.name}: trains again: the committed run summary's run trained on data hashed {old[:12]}, " \
           f"and {dataset} now hashes 000000000000 (made again on another machine, or changed)" in lines, lines


def test_a_store_that_is_gone_leaves_the_committed_summaries_in_charge(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue #19.5: a campaign resumed on a new machine, its MLflow store and datasets gone, must not train
    again what the committed run summaries report: their runs are finished (without making their data again),
    shared with the sweeps that plan the same run, and only a stress test, whose checkpoint is gone, trains."""
    from gns_bench.sweep.runner import SUMMARISED
    from gns_bench.sweep.summaries import RESTORED_FROM, summary_path

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'first.db'}")
    root = tmp_path / "sweeps"
    for folder in ("domains", "ablations", "stress"):
        (root / folder).mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", root / "tiers.toml")
    model = "[tiers.smoke.config.model]\nlatent_size = 8\nmlp_hidden_size = 6\n"
    (root / "domains" / "tiny.toml").write_text(f'description = "the model"\ndomain = "tiny"\n\n{model}')
    (root / "ablations" / "tiny.toml").write_text(f'description = "the same run"\ndomain = "tiny"\n\n{model}')
    (root / "stress" / "tiny.toml").write_text(
        f'description = "its stress tests"\ndomain = "tiny"\n\n[config.stress]\ntests = ["precision"]\n'
        f'precisions = ["fp32"]\nmax_trajectories = 1\nrollout_steps = 4\n\n{model}')
    domain, copy, stress = (load_sweep(root / folder / "tiny.toml", root) for folder in ("domains", "ablations",
                                                                                          "stress"))
    reports = tmp_path / "reports"
    quiet = dict(runs_root=tmp_path / "runs", progress=False, echo=lambda line: None)
    [trained] = run_sweep(domain, "smoke", data_root=tmp_path / "data", reports_root=reports, **quiet)
    assert summary_path(reports, "domain-tiny", "smoke").is_file()  # the runner wrote it as the run finished

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'new.db'}")  # a new machine: nothing kept
    data = tmp_path / "new-data"
    [planned] = domain.plan("smoke")
    _, status, _ = prepare(domain, "smoke", data, generate=False)
    assert status == {planned.name: "dataset missing"}  # what the runner knew before summaries counted
    _, status, _ = prepare(domain, "smoke", data, generate=False, reports_root=reports)
    assert status == {planned.name: SUMMARISED}
    assert [o.status for o in run_sweep(domain, "smoke", data_root=data, reports_root=reports, **quiet)] == ["SKIPPED"]
    assert not data.exists()  # known finished without generating its dataset again

    [shared] = run_sweep(copy, "smoke", data_root=data, reports_root=reports, **quiet)
    assert shared.status == "SHARED" and shared.metrics["test/rollout_mse"] == trained.metrics["rollout_mse"]
    record = tracking.get_run(shared.run_id)
    assert record.tags["shared_from"] == trained.run_id
    assert record.tags[RESTORED_FROM] == str(summary_path(reports, "domain-tiny", "smoke"))

    _, status, _ = prepare(stress, "smoke", data, progress=False, reports_root=reports)
    assert list(status.values()) == ["to run"]  # no checkpoint to stress-test: it trains the model itself

    (root / "domains" / "tiny.toml").write_text(f'description = "the model"\ndomain = "tiny"\n\n'
                                                f'{model.replace("latent_size = 8", "latent_size = 9")}')
    changed = load_sweep(root / "domains" / "tiny.toml", root)
    _, status, _ = prepare(changed, "smoke", data, generate=False, reports_root=reports)
    assert list(status.values()) == ["to run"]  # the summary's run is another run now
    _, status, _ = prepare(changed, "smoke", tmp_path / "no-data", generate=False, reports_root=reports)
    assert list(status.values()) == ["dataset missing"]  # and is not taken for it without data either


def test_compared_runs_wait_for_the_kind_of_machine_most_of_them_trained_on(
        sweeps: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A study's candidates (an ablation's arms alike) are compared with each other, and the verdicts compare
    runs on one CPU kind only: once they began on one kind, the rest wait for a machine of that kind, the dry run
    says so, and --any-cpu-kind trains them anyway."""
    from gns_bench import devices

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    (sweeps / "studies").mkdir()
    path = sweeps / "studies" / "kinds.toml"
    path.write_text(STUDY.replace('dataset_tier = "small"\n', ""))
    sweep = load_sweep(path)
    lines: list[str] = []
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, echo=lines.append)
    amd, intel = "family 25, model 17, stepping 1", "family 6, model 207, stepping 2"
    monkeypatch.setattr(devices, "cpu_identity", lambda *args: amd)
    [first] = run_sweep(sweep, "smoke", only=["candidate=plain-*"], **roots)
    assert first.status == "FINISHED" and tracking.get_run(first.run_id).tags["cpu"] == amd
    monkeypatch.setattr(devices, "cpu_identity", lambda *args: intel)  # the next session's machine
    outcomes = {o.name: o for o in run_sweep(sweep, "smoke", **roots)}
    assert outcomes["candidate=plain-seed0"].status == "SKIPPED"
    waiting = outcomes["candidate=more-data-seed0"]
    assert waiting.status == "WAITING" and amd in waiting.error, waiting
    assert [r.info.run_name for r in runs_of(sweep.experiment)] == ["candidate=plain-seed0"]  # nothing started
    assert any("--any-cpu-kind trains it here" in line for line in lines)
    _, status, _ = prepare(sweep, "smoke", tmp_path / "data", generate=False)
    assert status["candidate=more-data-seed0"] == f"waits for a machine of CPU kind {amd} (its sweep's compared " \
                                                 "runs trained there)"
    [ran] = [o for o in run_sweep(sweep, "smoke", any_kind=True, **roots) if o.status != "SKIPPED"]
    assert ran.status == "FINISHED" and tracking.get_run(ran.run_id).tags["cpu"] == intel


def test_a_started_run_resumes_only_on_the_kind_it_began_on(sweeps: Path, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """A run interrupted on one kind of machine waits for that kind to resume (its step times and bf16 arithmetic
    stay one machine's); in a sweep whose runs are not compared with each other, a run not yet begun trains on
    whatever machine is here."""
    from gns_bench import devices

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    path = sweeps / "tests" / "resume.toml"
    path.write_text(GRID.replace('"train.noise_std" = [0.0, 3e-4]\n', ""))
    sweep = load_sweep(path)
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, share=False,
                 echo=lambda line: None)
    amd, intel = "family 25, model 17, stepping 1", "family 6, model 207, stepping 2"
    monkeypatch.setattr(devices, "cpu_identity", lambda *args: amd)
    interrupted_at_step_7(monkeypatch, lambda: run_sweep(sweep, "smoke", **roots))
    (killed,) = runs_of(sweep.experiment)
    monkeypatch.setattr(devices, "cpu_identity", lambda *args: intel)
    outcomes = {o.name: o for o in run_sweep(sweep, "smoke", **roots)}
    assert outcomes[killed.info.run_name].status == "WAITING", outcomes
    assert "it began training there" in outcomes[killed.info.run_name].error
    [other] = [o for name, o in outcomes.items() if name != killed.info.run_name]
    assert other.status == "FINISHED"  # not a compared sweep: it trains here
    monkeypatch.setattr(devices, "cpu_identity", lambda *args: amd)
    [resumed] = [o for o in run_sweep(sweep, "smoke", **roots) if o.status != "SKIPPED"]
    assert resumed.status == "FINISHED" and resumed.run_id == killed.info.run_id


def test_a_bf16_run_waits_for_a_machine_with_a_bf16_unit(sweeps: Path, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Above the smoke tier, a run set to train in bf16 waits where bf16 products are slower than fp32's (no bf16
    unit: a fallback several times slower than fp32), its status giving the rates; an fp32 run of the same sweep
    trains; a machine with the unit trains it; --any-cpu-kind trains it anyway; smoke runs (seconds) never wait."""
    from gns_bench import autotune

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    path = sweeps / "tests" / "precision.toml"
    path.write_text(GRID.replace('"model.message_passing_steps" = [1, 2]\n"train.noise_std" = [0.0, 3e-4]',
                                 '"train.precision" = ["fp32", "bf16"]'))
    sweep = load_sweep(path)
    no_unit, unit = autotune.MatmulRates(fp32=35.0, bf16=2.0), autotune.MatmulRates(fp32=184.0, bf16=913.0)
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: no_unit)
    runs, status, _ = prepare(sweep, "small", tmp_path / "data", progress=False)
    [bf16] = [r.name for r in runs if r.config.train.precision == "bf16"]
    [fp32] = [r.name for r in runs if r.config.train.precision == "fp32"]
    assert status == {fp32: "to run", bf16: "waits for a machine with a bf16 unit (it trains in bf16, and its "
                                            "[4096, 128] x [128, 128] matmul ran 2 GFLOP/s in bf16 against 35 in "
                                            "fp32 here)"}
    _, status, _ = prepare(sweep, "small", tmp_path / "data", progress=False, any_kind=True)
    assert set(status.values()) == {"to run"}
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: unit)
    _, status, _ = prepare(sweep, "small", tmp_path / "data", progress=False)
    assert set(status.values()) == {"to run"}
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: no_unit)
    outcomes = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False,
                         echo=lambda line: None)
    assert [o.status for o in outcomes] == ["FINISHED", "FINISHED"]


BRANCHES = '''description = "a trunk and an annealed branch of it"
domain = "tiny"

[tiers.smoke.config.model]
latent_size = 8
mlp_hidden_size = 8

[tiers.smoke.config.train]
eval_every = 10
eval_trajectories = 1
eval_rollout_steps = 5
keep_checkpoints = true

[candidates.trunk]

[candidates.branch.config.train]
init_from = "runs:study-branches/smoke/candidate=trunk-seed{seed}/checkpoint-10.pt"
learning_rate_anneal_steps = 5
'''


def test_a_branch_waits_for_its_trunks_checkpoint_then_starts_from_it(sweeps: Path, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A candidate that starts from another run's kept checkpoint (`train.init_from = "runs:..."`, under the
    runs root wherever that is, so its key is the same on every machine) waits until that checkpoint exists,
    and trains in the same call as the run that writes it, after it."""
    from gns_bench.sweep.runner import dataset_run_key

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    (sweeps / "studies").mkdir()
    path = sweeps / "studies" / "branches.toml"
    path.write_text(BRANCHES)
    sweep = load_sweep(path)
    said: list[str] = []
    roots = dict(data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False, echo=said.append)
    [waiting] = run_sweep(sweep, "smoke", only=["candidate=branch-*"], **roots)  # its trunk not trained
    assert waiting.status == "WAITING" and waiting.error.endswith("candidate=trunk-seed0/checkpoint-10.pt"), waiting
    second = {o.name: o for o in run_sweep(sweep, "smoke", **roots)}
    assert second["candidate=trunk-seed0"].status == "FINISHED"
    branch = second["candidate=branch-seed0"]
    assert branch.status == "FINISHED", branch.error
    assert said.index("[1/1] candidate=trunk-seed0") < said.index("[1/1] candidate=branch-seed0"), said
    record = tracking.get_run(branch.run_id)
    trunk_checkpoint = tmp_path / "runs" / "study-branches" / "smoke" / "candidate=trunk-seed0" / "checkpoint-10.pt"
    assert record.params["train.init_from"] == str(trunk_checkpoint)  # what it started from, logged whole
    planned = next(r for r in sweep.plan("smoke") if r.name == "candidate=branch-seed0")
    assert record.tags["run_key"] == dataset_run_key(planned, tmp_path / "data")  # keyed by the runs: name
