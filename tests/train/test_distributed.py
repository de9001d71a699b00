"""Data parallelism: torchrun with 2 CPU processes matches 1 process with twice the batch."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import torch

from gns_bench.config import load_config
from gns_bench.train.loop import train

MODEL = ["model.message_passing_steps=2", "model.latent_size=32", "model.mlp_hidden_size=32",
         "train.learning_rate=1e-3", "train.steps=8", "train.log_every=4", "train.num_threads=1"]


def test_two_processes_equal_one_with_twice_the_batch(tiny_dataset: Path, tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
               "-m", "gns_bench.cli", "train", str(tiny_dataset), "--out", str(tmp_path / "ddp"), "--no-eval",
               "--experiment", "ddp-test", *MODEL, "train.batch_size=1"]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
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
