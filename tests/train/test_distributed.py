"""Data parallelism: torchrun with 2 CPU processes matches 1 process with twice the batch."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import psutil
import torch

from gns_bench.config import load_config
from gns_bench.train.loop import train

MODEL = ["model.message_passing_steps=2", "model.latent_size=32", "model.mlp_hidden_size=32",
         "train.learning_rate=1e-3", "train.steps=8", "train.log_every=4", "train.num_threads=1"]


def test_two_processes_equal_one_with_twice_the_batch(tiny_dataset: Path, tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONFAULTHANDLER": "1"}
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
               "-m", "gns_bench.cli", "train", str(tiny_dataset), "--out", str(tmp_path / "ddp"), "--no-eval",
               "--experiment", "ddp-test", *MODEL, "train.batch_size=1"]
    returncode, stderr = _run_or_dump_stacks(command, env, timeout_s=300)
    assert returncode == 0, stderr[-6000:]
    single = train(load_config(None, MODEL + ["train.batch_size=2"]), tiny_dataset, tmp_path / "one",
                   progress=False)
    ddp_state = torch.load(tmp_path / "ddp" / "checkpoint.pt", weights_only=False)
    one_state = torch.load(single.checkpoint, weights_only=False)
    assert ddp_state["step"] == one_state["step"] == 8
    differences = [float((ddp_state["model"][k] - v).abs().max()) for k, v in one_state["model"].items()]
    assert max(differences) < 1e-5, max(differences)
    initial = train(load_config(None, MODEL + ["train.batch_size=2", "train.steps=0"]), tiny_dataset,
                    tmp_path / "init", progress=False)
    init_state = torch.load(initial.checkpoint, weights_only=False)
    moved = max(float((v - ddp_state["model"][k]).abs().max()) for k, v in init_state["model"].items())
    assert moved > 1e-3, "training must have moved the parameters for the comparison to mean anything"


TEARDOWN = """
import sys
import torch
from gns_bench.train import distributed

group = distributed.from_environment(torch.device("cpu"))
model = group.wrap(torch.nn.Linear(3, 2))
model(torch.ones(1, 3)).sum().backward()
try:
    group.close()
except RuntimeError as error:
    assert "still alive" in str(error), error
else:
    raise SystemExit("close() accepted a live DDP wrapper")
del model
group.close()
assert not torch.distributed.is_initialized()
print("closed rank", group.rank, file=sys.stderr)
"""


def test_close_refuses_while_a_ddp_wrapper_is_alive(tmp_path: Path) -> None:
    """A DDP reducer freed after its gloo group deadlocks the rank; close() must refuse that order."""
    script = tmp_path / "teardown.py"
    script.write_text(TEARDOWN)
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", str(script)]
    returncode, stderr = _run_or_dump_stacks(command, {**os.environ, "OMP_NUM_THREADS": "1",
                                                       "PYTHONFAULTHANDLER": "1"}, timeout_s=120)
    assert returncode == 0, stderr[-6000:]
    assert stderr.count("closed rank") == 2, stderr[-3000:]


def _run_or_dump_stacks(command: list[str], env: dict[str, str], timeout_s: float) -> tuple[int | None, str]:
    """Run `command`; if it hangs, SIGABRT every process under it so that faulthandler prints each rank's
    Python stacks into stderr, and return that (returncode None) for the failure message."""
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _, stderr = process.communicate(timeout=timeout_s)
        return process.returncode, stderr
    except subprocess.TimeoutExpired:
        ranks = psutil.Process(process.pid).children(recursive=True)  # torchrun starts them in new sessions
        for rank in ranks:
            with contextlib.suppress(psutil.NoSuchProcess):
                rank.send_signal(signal.SIGABRT)
        psutil.wait_procs(ranks, timeout=30)
        process.kill()
        _, stderr = process.communicate()
        return None, f"hung for {timeout_s:.0f} s; stacks at SIGABRT:\n{stderr}"
