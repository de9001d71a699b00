"""`train.precision` / `train.compile = "auto"`: measured, cached per machine and model, recorded, resumed."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gns_bench import autotune
from gns_bench.config import load_config
from gns_bench.train.loop import train

QUICK = ["model.message_passing_steps=1", "model.latent_size=16", "model.mlp_hidden_size=16", "train.log_every=5"]


def test_pick_counts_compile_time_against_the_steps_left() -> None:
    timings = {"fp32": 1.0, "bf16": 0.5, "bf16+compile": 0.4}
    assert autotune.pick(timings, compile_seconds=60.0, steps_left=100) == ("bf16", False)  # 60 s > 100 x 0.1 s
    assert autotune.pick(timings, compile_seconds=60.0, steps_left=10_000) == ("bf16", True)
    assert autotune.pick({"fp32": 0.3, "bf16": 0.5}, 0.0, 10) == ("fp32", False)


def test_one_stalled_step_does_not_decide_the_probe() -> None:
    # a step of 0.5 s, one of which stalled for 170 s (the campaign paused with SIGSTOP mid-probe), after a
    # warm-up whose first step compiled for 40 s
    durations = iter([40.5, 0.5, 0.5] + [0.5, 0.5, 170.5, 0.5, 0.5, 0.5, 0.5, 0.5])
    now = [0.0]

    def step() -> None:
        now[0] += next(durations)

    seconds, compiling = autotune._time(step, clock=lambda: now[0])
    assert seconds == pytest.approx(0.5) and compiling == pytest.approx(40.0)
    assert autotune.TIMED_STEPS == 8  # the durations above cover the warm-up and every timed step
    with pytest.raises(StopIteration):
        step()


def test_auto_probes_once_then_reads_its_cache_and_a_resume_keeps_the_choice(
        tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    probed: list[str] = []
    real_choose = autotune.choose

    def fake_timings(config, simulator, step_fn, nodes, device, steps_left, use_cache=True):
        step_fn(simulator, "bf16")  # the probe's step runs on the model it is given
        probed.append(autotune.cache_key(config, simulator, nodes, device))
        return real_choose(config, simulator, step_fn, nodes, device, steps_left, use_cache=use_cache)

    monkeypatch.setattr(autotune, "choose", fake_timings)
    config = load_config(None, QUICK + ["train.steps=10", "train.precision=auto"])
    first = train(config, tiny_dataset, tmp_path / "a", progress=False)
    assert first.speed.source == "probed" and set(first.speed.seconds_per_step) == {"fp32", "bf16"}
    assert first.speed.precision in ("fp32", "bf16") and first.speed.compile is False
    assert (tmp_path / "cache" / "autotune.json").is_file()
    second = train(config, tiny_dataset, tmp_path / "b", progress=False)
    assert second.speed.source == "cached" and second.speed.precision == first.speed.precision
    assert probed[0] == probed[1] and f"x{torch.get_num_threads()}; torch" in probed[0]  # machine and threads
    longer = load_config(None, QUICK + ["train.steps=20", "train.precision=auto"])
    resumed = train(longer, tiny_dataset, tmp_path / "a", resume=True, progress=False)
    assert resumed.speed.precision == first.speed.precision and resumed.speed.source == "probed"  # from the ckpt
    saved = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    assert saved["speed"]["precision"] == first.speed.precision


def test_nothing_auto_means_no_probe(tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    result = train(load_config(None, QUICK + ["train.steps=5", "train.precision=bf16"]), tiny_dataset,
                   tmp_path / "run", progress=False)
    assert (result.speed.precision, result.speed.compile, result.speed.source) == ("bf16", False, "given")
    assert not (tmp_path / "cache").exists()
