"""The CLI end to end on the tiny domain, tracked in MLflow, and its error handling."""

from __future__ import annotations

from pathlib import Path

import mlflow
import pytest
from mlflow.tracking import MlflowClient

from gns_bench import tracking
from gns_bench.cli import COMMANDS, build_parser, main

TRAIN = ["model.message_passing_steps=1", "model.latent_size=16", "model.mlp_hidden_size=16",
         "train.steps=20", "train.log_every=5", "eval.max_trajectories=1"]


def client() -> MlflowClient:
    return MlflowClient(tracking_uri=tracking.tracking_uri())


def test_every_subcommand_has_help(capsys: pytest.CaptureFixture) -> None:
    for command in COMMANDS:
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args([command, "--help"])
        assert info.value.code == 0
        assert command in capsys.readouterr().out


def test_train_evaluate_rollout_logged_to_mlflow(tiny_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["train", str(tiny_dataset), *TRAIN, "train.eval_every=10", "--out", str(out),
                 "--experiment", "cli-test"]) == 0
    run_id = (out / "mlflow_run_id").read_text().strip()
    run = client().get_run(run_id)
    assert run.info.status == "FINISHED"
    assert run.data.params["model.message_passing_steps"] == "1"
    assert run.data.params["model.connectivity_radius"] == "0.1"  # resolved from the dataset, logged as a number
    curve = client().get_metric_history(run_id, "curve/rollout_mse")  # error against training time
    assert [m.step for m in curve] == [0, 10, 20]
    assert [m.step for m in client().get_metric_history(run_id, "curve/train_seconds")] == [0, 10, 20]
    assert run.data.params["train.noise_std"] == "0.0003"
    assert run.data.tags["dataset_hash"] and run.data.tags["torch_version"] and run.data.tags["git_sha"]
    assert "test/rollout_mse" in run.data.metrics and "test/one_step_mse" in run.data.metrics
    history = client().get_metric_history(run_id, "train_loss")
    assert [m.step for m in history] == [5, 10, 15, 20]
    artifacts = {a.path for a in client().list_artifacts(run_id)}
    assert {"checkpoint", "evaluation", "config.json"} <= artifacts
    evaluation = {a.path for a in client().list_artifacts(run_id, "evaluation")}
    assert "evaluation/test_rollouts.npz" in evaluation and "evaluation/test_rollout_best.png" in evaluation

    assert main(["evaluate", str(out), str(tiny_dataset), "--split", "valid", "--experiment", "cli-test"]) == 0
    runs = mlflow.search_runs(experiment_names=["cli-test"], filter_string="tags.kind = 'evaluate'",
                              output_format="list")
    assert len(runs) == 1 and "valid/rollout_mse" in runs[0].data.metrics

    stem = tmp_path / "roll"
    assert main(["rollout", str(out / "checkpoint.pt"), str(tiny_dataset), "--steps", "10", "--out", str(stem)]) == 0
    assert Path(f"{stem}.npz").stat().st_size > 0 and Path(f"{stem}.png").stat().st_size > 1000


def test_resume_continues_the_same_mlflow_run(tiny_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    base = [str(tiny_dataset), *TRAIN[:3], "train.log_every=5", "--out", str(out), "--experiment", "resume",
            "--no-eval"]
    assert main(["train", *base, "train.steps=10"]) == 0
    first = (out / "mlflow_run_id").read_text()
    assert main(["train", *base, "train.steps=20", "--resume"]) == 0
    assert (out / "mlflow_run_id").read_text() == first
    history = client().get_metric_history(first.strip(), "train_loss")
    assert [m.step for m in history] == [5, 10, 15, 20]
    rate = client().get_run(first.strip()).data.metrics["train/steps_per_second"]
    assert rate > 0
    # resumed with no step left to train (e.g. only its evaluation was cut short): the rate stands
    assert main(["train", *base, "train.steps=20", "--resume"]) == 0
    assert client().get_run(first.strip()).data.metrics["train/steps_per_second"] == rate


def test_failing_run_is_marked_failed(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError):
        with tracking.start_run("fail-test", "boom") as run:
            raise RuntimeError("boom")
    failed = client().get_run(run.run_id)
    assert failed.info.status == "FAILED" and "boom" in failed.data.tags["error"]


def test_bad_dataset_gives_a_clear_error_and_leaves_nothing_behind(
        tmp_path: Path, tiny_dataset: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    import h5py

    monkeypatch.chdir(tmp_path)
    assert main(["train", str(tmp_path / "nowhere"), "train.steps=1"]) == 2
    assert "nowhere/metadata.json: no such file" in capsys.readouterr().err
    assert main(["train", str(tmp_path), "model.latent_size=0"]) == 2
    assert "model.latent_size: must be > 0" in capsys.readouterr().err
    broken = shutil.copytree(tiny_dataset, tmp_path / "broken")  # a train split with a NaN in it
    with h5py.File(broken / "train.h5", "r+") as f:
        f["00000/position"][3, 0, 0] = float("nan")
    assert main(["train", str(broken), "train.steps=1", "--experiment", "refused"]) == 2
    assert "train.h5" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()  # no run folder for input refused before training
    assert tracking.search_runs(experiment="refused") == []  # and no MLflow run


def test_sigterm_interrupts_like_ctrl_c() -> None:
    """SLURM and `kill` send SIGTERM: the command must stop the way Ctrl-C stops it (checkpoint, KILLED)."""
    import os
    import signal
    import time

    from gns_bench.cli import interrupt_on_signals

    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job (`nohup ... &`) starts
    try:
        interrupt_on_signals()
        for signum in (signal.SIGTERM, signal.SIGINT):
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), signum)
                time.sleep(1)  # the handler raises at once; this only bounds the wait
    finally:
        signal.signal(signal.SIGTERM, before[0])
        signal.signal(signal.SIGINT, before[1])


def test_ui_stops_with_its_web_server_on_sigterm(tmp_path: Path) -> None:
    """`gns-bench ui` runs MLflow's web server as child processes; SIGTERM to gns-bench takes them all down."""
    import signal
    import socket
    import subprocess
    import sys
    import time

    import psutil

    with socket.socket() as probe:  # a free port
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    ui = subprocess.Popen([sys.executable, "-c", "from gns_bench.cli import run; raise SystemExit(run())", "ui",
                           "--port", str(port)], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            with socket.socket() as client:
                if client.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.5)
        else:
            raise AssertionError("the MLflow UI never listened")
        server = psutil.Process(ui.pid).children(recursive=True)
        assert server, "the UI runs in child processes"
        ui.send_signal(signal.SIGTERM)
        ui.wait(timeout=30)
        gone, alive = psutil.wait_procs(server, timeout=15)
        assert not alive, f"left running: {[p.pid for p in alive]}"
    finally:
        if ui.poll() is None:
            ui.kill()


def test_generate_overwrite_replaces_the_default_dataset_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["generate", "tiny", "--tier", "smoke"]) == 0
    made = tmp_path / "data" / "tiny-smoke-s0"
    (made / "stray.txt").write_text("left by hand")
    assert main(["generate", "tiny", "--tier", "smoke"]) == 0 and (made / "stray.txt").exists()  # reused
    assert main(["generate", "tiny", "--tier", "smoke", "--overwrite"]) == 0  # no --out: the default folder
    assert not (made / "stray.txt").exists() and (made / "metadata.json").exists()
    capsys.readouterr()
    assert main(["generate", "notadomain", "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "unknown domain 'notadomain'" in err and "tiny" in err and "waterdrop" in err


def test_the_summary_prints_each_metric_beside_its_baseline_over_the_same_steps() -> None:
    """A rollout a monitor stopped at step 70 of 294 is compared with constant velocity over those 70 steps,
    not the whole horizon's baseline."""
    from gns_bench.cli import summary_lines

    lines = summary_lines({"one_step_mse": 1e-8, "one_step_mse_moving": 2e-8, "rollout_mse": 0.002858,
                           "rollout_mse_moving": 0.003, "rollout_steps": 70.0, "rollout_stopped": 1.0,
                           "baseline_cv_rollout_mse": 0.07104, "baseline_cv_same_steps_mse": 0.0150})
    assert lines[2] == "constant velocity  0.015 over the same steps: GNS / constant velocity = 0.191x"
    assert "over 70 steps" in lines[1] and "stopped" in lines[1] and "0.07104" not in "".join(lines)
    assert len(lines) == 3  # no diagnostics logged: no lines for them
    hovering = summary_lines({"rollout_mse": 0.01, "baseline_cv_same_steps_mse": 0.02, "gravity_ratio": 0.74,
                              "rollout_gravity_ratio": -0.16, "com_fall_ratio": -0.04, "wall_pass_fraction": 0.33})
    assert "0.74 of g on true windows, -0.16 along the rollout" in hovering[3]
    assert "fell -0.04 of the truth's" in hovering[4] and "33% of moving particles" in hovering[5]


@pytest.mark.parametrize("architecture", ["cconv", "dpi"])
def test_a_baseline_architecture_trains_and_evaluates_end_to_end(architecture: str, tiny_dataset: Path,
                                                                tmp_path: Path) -> None:
    """`model.architecture` switches the learned simulator (Sec. 5.5 baselines) inside the same training loop,
    evaluation, rollouts and MLflow logging."""
    out = tmp_path / architecture
    assert main(["train", str(tiny_dataset), f"model.architecture={architecture}", "train.steps=6",
                 "train.log_every=3", "eval.max_trajectories=1", "eval.rollout_steps=5", "eval.one_step_windows=3",
                 "--out", str(out), "--experiment", "baselines-test"]) == 0
    run = client().get_run((out / "mlflow_run_id").read_text().strip())
    assert run.info.status == "FINISHED" and run.data.params["model.architecture"] == architecture
    assert {"test/rollout_mse", "test/one_step_mse", "train_loss"} <= set(run.data.metrics)
    assert [m.step for m in client().get_metric_history(run.info.run_id, "train_loss")] == [3, 6]
