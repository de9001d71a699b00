"""`train.precision` / `train.compile = "auto"`: measured, cached per machine and model, recorded, resumed."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gns_bench import autotune
from gns_bench.config import load_config
from gns_bench.train.loop import train

FAST_BF16 = autotune.MatmulRates(fp32=184.0, bf16=913.0)  # AMD EPYC family 26 model 2's bench, GFLOP/s
NO_BF16_UNIT = autotune.MatmulRates(fp32=35.0, bf16=2.0)  # AMD EPYC family 25 model 1 (AVX2 only)
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
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: FAST_BF16)  # bf16 is probed
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
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: FAST_BF16)
    result = train(load_config(None, QUICK + ["train.steps=5", "train.precision=bf16"]), tiny_dataset,
                   tmp_path / "run", progress=False)
    assert (result.speed.precision, result.speed.compile, result.speed.source) == ("bf16", False, "given")
    assert not (tmp_path / "cache").exists()


def probed_precisions(rates: autotune.MatmulRates, precision: str, monkeypatch: pytest.MonkeyPatch
                      ) -> tuple[autotune.SpeedSettings, list[str]]:
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: rates)
    probed: list[str] = []
    config = load_config(None, QUICK + [f"train.precision={precision}"]).train
    model = torch.nn.Linear(2, 2)
    model.dim = 2  # what the cache key reads of a simulator
    choice = autotune.choose(config, model, lambda m, p: probed.append(p), 100, torch.device("cpu"), 1000,
                             use_cache=False)
    return choice, probed


def test_bf16_is_probed_only_where_its_products_outrun_fp32s(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    choice, probed = probed_precisions(FAST_BF16, "auto", monkeypatch)
    assert set(probed) == {"fp32", "bf16"} and choice.note == ""
    choice, probed = probed_precisions(NO_BF16_UNIT, "auto", monkeypatch)
    assert probed == [] and (choice.precision, choice.compile) == ("fp32", False)  # nothing left to compare
    assert choice.note == ("bf16 not probed: its [4096, 128] x [128, 128] matmul ran 2 GFLOP/s in bf16 against 35 "
                           "in fp32 here")
    assert choice.note in choice.describe()


def test_bf16_asked_for_on_a_machine_without_a_bf16_unit_trains_in_bf16_and_says_so(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    with pytest.warns(UserWarning, match="no fast bf16 matmul"):
        choice, probed = probed_precisions(NO_BF16_UNIT, "bf16", monkeypatch)
    assert (choice.precision, choice.source, probed) == ("bf16", "given", [])
    assert "bf16 as configured, though its [4096, 128] x [128, 128] matmul ran 2 GFLOP/s" in choice.describe()


def test_matmul_rates_are_measured_once_per_machine(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    rates = autotune.matmul_rates(torch.device("cpu"))
    assert rates.fp32 > 0 and rates.bf16 > 0

    def no_measuring(*args, **kwargs):
        raise AssertionError("measured again")

    monkeypatch.setattr(torch, "randn", no_measuring)
    assert autotune.matmul_rates(torch.device("cpu")) == rates  # from the cache
    with pytest.raises(AssertionError, match="measured again"):
        autotune.matmul_rates(torch.device("cpu"), use_cache=False)
