"""Bad input, as a new user meets it: each case damages a copy of the tiny dataset (or the command line), runs
`gns-bench train`, and expects exit code 2 before training, a message that names the file and the field, and
nothing left behind (no run directory, no MLflow run)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import pytest

from gns_bench import tracking
from gns_bench.cli import main

QUICK = ["model.message_passing_steps=1", "model.latent_size=16", "model.mlp_hidden_size=16", "train.steps=4",
         "train.log_every=2", "eval.max_trajectories=1", "eval.rollout_steps=3", "eval.one_step_windows=1",
         "eval.distribution_steps=0"]


def edit_metadata(**changes):
    def damage(data: Path) -> None:
        meta = json.loads((data / "metadata.json").read_text())
        meta.update(changes)
        (data / "metadata.json").write_text(json.dumps(meta))
    return damage


def edit_array(split: str, field: str, index: tuple, value: float):
    def damage(data: Path) -> None:
        with h5py.File(data / f"{split}.h5", "r+") as f:
            array = f[f"00000/{field}"]
            values = array[()]
            values[index] = value
            array[...] = values
    return damage


def truncate(split: str):
    def damage(data: Path) -> None:
        path = data / f"{split}.h5"
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    return damage


def remove(split: str):
    def damage(data: Path) -> None:
        (data / f"{split}.h5").unlink()
    return damage


@dataclass
class Case:
    name: str
    damage: Callable[[Path], None]
    words: tuple[str, ...]  # what the message must say (file, field, what was expected)
    extra: tuple[str, ...] = ()  # more command-line arguments


CASES = [
    Case("radius as a string", edit_metadata(default_connectivity_radius="0.1"),
         ("metadata.json", "default_connectivity_radius", "a positive number")),
    Case("dt as a string", edit_metadata(dt="0.0025"), ("metadata.json", "'dt'", "positive number")),
    Case("walls not a boolean", edit_metadata(walls="yes"), ("metadata.json", "'walls'", "true or false")),
    Case("statistics of the wrong length", edit_metadata(vel_std=[1.0]), ("metadata.json", "vel_std", "2 finite")),
    Case("sequence_length beyond the stored frames", edit_metadata(sequence_length=200),
         ("train.h5", "position", "sequence_length", "201")),
    Case("a corrupt test split", truncate("test"), ("test.h5", "unreadable or truncated")),
    Case("non-finite test positions", edit_array("test", "position", (2, 1, 0), float("nan")),
         ("test.h5", "position", "NaN")),
    Case("no test split", remove("test"), ("test.h5", "no such file")),
    Case("a corrupt validation split", truncate("valid"), ("valid.h5", "unreadable or truncated")),
    Case("validation positions out of bounds", edit_array("valid", "position", (0, 0, 1), 40.0),
         ("valid.h5", "position", "outside the metadata bounds")),
    Case("one float of the training data changed", edit_array("train", "position", (3, 2, 0), 0.5),
         ("metadata.json", "content_hash", "split(s) train changed", "gns-bench rehash")),
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_refused_before_training(case: Case, tiny_dataset: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture) -> None:
    data = shutil.copytree(tiny_dataset, tmp_path / "data")
    case.damage(data)
    out = tmp_path / "run"
    experiment = f"bad-{case.name.replace(' ', '-')}"
    code = main(["train", str(data), *QUICK, "--out", str(out), "--experiment", experiment, *case.extra])
    err = capsys.readouterr().err
    assert code == 2, err
    for word in case.words:
        assert word in err, f"{word!r} not in: {err}"
    assert not out.exists()  # nothing left behind
    assert tracking.search_runs(experiment=experiment) == []


def test_out_naming_a_file_says_a_directory_is_wanted(tiny_dataset: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "run.txt"
    out.write_text("mine")
    assert main(["train", str(tiny_dataset), *QUICK, "--out", str(out), "--experiment", "file-out"]) == 2
    assert "is a file; the run's output (--out) is a directory" in capsys.readouterr().err
    assert out.read_text() == "mine" and tracking.search_runs(experiment="file-out") == []


def test_an_override_without_a_value_says_key_equals_value(tiny_dataset: Path, capsys: pytest.CaptureFixture):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", str(tiny_dataset), "--no-eval", "train.steps"])
    assert exit_info.value.code == 2
    assert "override 'train.steps' has no value" in capsys.readouterr().err
    assert main(["train", str(tiny_dataset), "train.steps"]) == 2  # before the options, parsed as an override
    assert "train.steps=1000" in capsys.readouterr().err


def test_changed_data_rehashed_on_purpose_trains(tiny_dataset: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    data = shutil.copytree(tiny_dataset, tmp_path / "data")
    before = json.loads((data / "metadata.json").read_text())["content_hash"]
    edit_array("train", "position", (3, 2, 0), 0.5)(data)
    assert main(["train", str(data), *QUICK, "--out", str(tmp_path / "a"), "--no-eval"]) == 2
    assert main(["rehash", str(data)]) == 0
    after = json.loads((data / "metadata.json").read_text())["content_hash"]
    assert after != before and after in capsys.readouterr().out
    assert main(["train", str(data), *QUICK, "--out", str(tmp_path / "b"), "--no-eval"]) == 0


def test_a_failed_resume_leaves_a_finished_run_finished(tiny_dataset: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "run"
    base = ["train", str(tiny_dataset), *QUICK, "--out", str(out), "--experiment", "resume-refused", "--no-eval"]
    assert main(base) == 0
    run_id = (out / "mlflow_run_id").read_text().strip()
    assert tracking.get_run(run_id).status == "FINISHED"
    (out / "checkpoint.pt").write_bytes(b"not a checkpoint")
    assert main([*base, "--resume"]) == 2
    assert "checkpoint" in capsys.readouterr().err
    assert tracking.get_run(run_id).status == "FINISHED"


def test_a_killed_run_is_marked_killed_by_the_next_command(tiny_dataset: Path, tmp_path: Path) -> None:
    """A process killed with SIGKILL leaves its run RUNNING and its owner file behind; the next command on that
    directory finds no live process and ends the run KILLED."""
    out = tmp_path / "run"
    base = ["train", str(tiny_dataset), *QUICK, "--out", str(out), "--experiment", "killed", "--no-eval"]
    assert main(base) == 0
    run_id = (out / "mlflow_run_id").read_text().strip()
    from mlflow.tracking import MlflowClient

    MlflowClient(tracking_uri=tracking.tracking_uri()).update_run(run_id, status="RUNNING")  # as if killed
    (out / "owner.pid").write_text(f"{2**22 + 12345}\n")  # a process id no process has
    assert main([*base, "train.steps=6", "--resume"]) == 0
    history = [record.status for record in tracking.search_runs(experiment="killed")]
    assert history == ["FINISHED"]  # resumed: the same run, now finished again
    (out / "owner.pid").write_text(f"{2**22 + 12345}\n")
    MlflowClient(tracking_uri=tracking.tracking_uri()).update_run(run_id, status="RUNNING")
    from gns_bench.pipeline import end_if_abandoned

    assert end_if_abandoned(out) and tracking.get_run(run_id).status == "KILLED"
    assert end_if_abandoned(out) is False  # ended once
