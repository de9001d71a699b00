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


def test_thread_counts_cover_one_the_powers_of_two_and_every_core() -> None:
    assert autotune.thread_counts(1) == [1]
    assert autotune.thread_counts(2) == [1, 2]
    assert autotune.thread_counts(6) == [1, 2, 4, 6]
    assert autotune.thread_counts(16) == [1, 2, 4, 8, 16]


# seconds a training step took by thread count: an AVX2-only AMD EPYC's in one session (family 25 model 1, 2,000
# particles; in the next the second thread helped), and a machine where the second thread helps a little
AVX2_EPYC = {1: 2.64, 2: 4.03}
TWO_HELP_A_LITTLE = {1: 1.02, 2: 1.0}


def fake_clock(seconds_by_threads: dict[int, float]):
    """A step that takes, on a clock of its own, what a step took on `seconds_by_threads`'s machine at torch's
    current thread count."""
    now = [0.0]

    def step() -> None:
        now[0] += seconds_by_threads[torch.get_num_threads()]

    return step, lambda: now[0]


@pytest.mark.parametrize("machine, chosen", [(AVX2_EPYC, 1), (TWO_HELP_A_LITTLE, 2), ({1: 0.97, 2: 1.0}, 2)])
def test_the_thread_probe_picks_fewer_threads_only_where_they_are_clearly_faster(
        machine: dict[int, float], chosen: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(autotune, "load_average", lambda: 0.4)  # a quiet machine, whatever the test machine's load
    before = torch.get_num_threads()
    try:
        step, clock = fake_clock(machine)
        choice = autotune.choose_threads(step, "a machine | a model", 2, clock=clock)
        assert choice.threads == chosen and torch.get_num_threads() == chosen  # set before it returns
        assert choice.source == "probed" and choice.seconds_per_step == pytest.approx(
            {str(k): v for k, v in machine.items()})
        assert f"{chosen} thread" in choice.describe() and "a step by thread count" in choice.describe()

        def must_not_run() -> None:
            raise AssertionError("a cached choice must not time steps")

        again = autotune.choose_threads(must_not_run, "a machine | a model", 2)
        assert (again.threads, again.source) == (chosen, "cached")
        assert autotune.choose_threads(must_not_run, "a machine | a model", 1).source == "one core"
    finally:
        torch.set_num_threads(before)


def test_a_thread_probe_on_a_loaded_machine_is_used_but_not_cached(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(autotune, "load_average", lambda: 4.4)  # another 2-thread job on the 2 cores
    before = torch.get_num_threads()
    try:
        step, clock = fake_clock(AVX2_EPYC)
        choice = autotune.choose_threads(step, "a machine | a model", 2, clock=clock)
        assert choice.threads == 1 and choice.source == "probed under load 4.4, not cached"
        assert "(probed under load 4.4, not cached: 1 2.64 s" in choice.describe()
        again = autotune.choose_threads(step, "a machine | a model", 2, clock=clock)
        assert again.source.startswith("probed under load")  # timed again, not read back
    finally:
        torch.set_num_threads(before)


@pytest.fixture
def probe_with(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """`probe_with(machine)`: thread probes from here on time a step as `machine` ({threads: seconds}) does, on
    a quiet machine of 2 cores, whatever the test machine has; torch's thread count restored afterwards."""
    from gns_bench.train import loop

    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(loop, "usable_cores", lambda: 2)
    monkeypatch.setattr(autotune, "load_average", lambda: 0.4)
    monkeypatch.setattr(loop, "set_threads", lambda requested: torch.set_num_threads(requested or 2) or
                        torch.get_num_threads())

    def probe_with(machine: dict[int, float]) -> None:
        def timed(step, clock=None):
            step()  # the probe's step runs, its time taken from the machine described
            return machine[torch.get_num_threads()], 0.0

        monkeypatch.setattr(autotune, "_time", timed)

    before = torch.get_num_threads()
    yield probe_with
    torch.set_num_threads(before)


def test_num_threads_auto_trains_on_the_probed_count_and_a_resume_keeps_it(
        tiny_dataset: Path, tmp_path: Path, probe_with) -> None:
    seen: list[int] = []  # torch's thread count at each logged step

    def on_log(step: int, metrics: dict) -> None:
        seen.append(torch.get_num_threads())

    probe_with(AVX2_EPYC)
    config = load_config(None, QUICK + ["train.steps=10", "train.num_threads=auto"])
    first = train(config, tiny_dataset, tmp_path / "a", progress=False, on_log=on_log)
    assert first.speed.threads.threads == 1 and first.speed.threads.source == "probed"
    assert seen and set(seen) == {1}
    assert "1 thread (probed: 1 2.64 s, 2 4.03 s a step by thread count)" in first.speed.describe()
    saved = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    assert saved["speed"]["threads"]["threads"] == 1
    probe_with(TWO_HELP_A_LITTLE)  # the machine changed its mind: a resume must not ask again
    seen.clear()
    torch.set_num_threads(2)
    longer = load_config(None, QUICK + ["train.steps=20", "train.num_threads=auto"])
    resumed = train(longer, tiny_dataset, tmp_path / "a", resume=True, progress=False, on_log=on_log)
    assert resumed.speed.threads.threads == 1 and set(seen) == {1}
    fixed = train(load_config(None, QUICK + ["train.steps=5", "train.num_threads=2"]), tiny_dataset,
                  tmp_path / "b", progress=False)
    assert fixed.speed.threads is None and torch.get_num_threads() == 2  # a given count is not probed
    probe_with(AVX2_EPYC)  # resumed with "auto": the count it never chose is probed, the rest kept
    switched = train(load_config(None, QUICK + ["train.steps=10", "train.num_threads=auto"]), tiny_dataset,
                     tmp_path / "b", resume=True, progress=False)
    assert switched.speed.threads.threads == 1 and torch.get_num_threads() == 1
    assert (switched.speed.precision, switched.speed.compile) == (fixed.speed.precision, fixed.speed.compile)


def test_a_run_tagged_before_its_thread_count_was_chosen_names_the_count_it_trained_on(
        tiny_dataset: Path, tmp_path: Path, probe_with) -> None:
    from gns_bench import tracking
    from gns_bench.pipeline import train_run

    probe_with(AVX2_EPYC)
    torch.set_num_threads(2)  # the run's tags are taken at 2 threads, before the probe picks 1
    config = load_config(None, QUICK + ["train.steps=5", "train.num_threads=auto"])
    summary = train_run(config, tiny_dataset, tmp_path / "run", evaluate_after=False, progress=False)
    assert tracking.get_run(summary.run_id).tags["hardware"].endswith(", 1 thread")
