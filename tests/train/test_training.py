"""Training: it learns the tiny domain, and an interrupted run resumes on the same loss curve."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gns_bench.config import ConfigError, load_config
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, load_split, read_metadata
from gns_bench.evaluate.evaluate import evaluate
from gns_bench.train.checkpoints import load_checkpoint, load_simulator
from gns_bench.train.loop import learning_rate, train
from gns_bench.train.rate import measure_step_rate, steady_rate

QUICK = ["model.message_passing_steps=2", "model.latent_size=64", "model.mlp_hidden_size=64",
         "train.batch_size=8", "train.learning_rate=2e-3", "train.learning_rate_decay_steps=2000",
         "train.noise_std=1e-5", "train.log_every=50"]


def test_learning_rate_schedule() -> None:
    config = load_config().train
    assert learning_rate(0, config) == pytest.approx(1e-4)
    assert learning_rate(5_000_000, config) == pytest.approx((1e-4 - 1e-6) * 0.1 + 1e-6)
    assert learning_rate(10**9, config) == pytest.approx(1e-6)


def test_training_learns_and_beats_constant_velocity(tiny_dataset: Path, tmp_path: Path) -> None:
    config = load_config(None, QUICK + ["train.steps=1200"])
    result = train(config, tiny_dataset, tmp_path / "run", progress=False)
    first, last = np.mean(result.losses[:20]), np.mean(result.losses[-100:])
    assert last < first / 10, f"training loss fell only from {first:.3g} to {last:.3g}"
    simulator, config, _ = load_simulator(result.checkpoint)
    evaluation = evaluate(simulator, load_split(tiny_dataset, "test"), config.eval, progress=False)
    m = evaluation.metrics
    assert m["rollout_mse"] < 0.1 * m["baseline_cv_rollout_mse"], m
    assert m["one_step_mse"] < m["rollout_mse"]


def test_interrupt_and_resume_continues_the_same_loss_curve(tiny_dataset: Path, tmp_path: Path) -> None:
    config = load_config(None, QUICK + ["train.steps=30", "train.checkpoint_every=7"])
    straight = train(config, tiny_dataset, tmp_path / "straight", progress=False)
    first_half = load_config(None, QUICK + ["train.steps=13", "train.checkpoint_every=7"])
    part = train(first_half, tiny_dataset, tmp_path / "resumed", progress=False)
    rest = train(config, tiny_dataset, tmp_path / "resumed", resume=True, progress=False)
    assert rest.start_step == 13 and rest.final_step == 30
    assert part.losses + rest.losses == straight.losses  # bit for bit


def test_a_run_stopped_between_two_log_points_logs_the_same_curve(tiny_dataset: Path, tmp_path: Path) -> None:
    """The logged loss is the mean since the last logged point; a resume carries the steps since then (the
    checkpoint's `log_window`), so every logged point equals the uninterrupted run's."""
    config = load_config(None, QUICK + ["train.steps=30", "train.checkpoint_every=7", "train.log_every=5"])
    straight: list[tuple[int, float]] = []
    train(config, tiny_dataset, tmp_path / "straight", progress=False,
          on_log=lambda step, m: straight.append((step, m["train_loss"])))
    resumed: list[tuple[int, float]] = []
    train(config, tiny_dataset, tmp_path / "resumed", progress=False, stop_after=13,  # between 10 and 15
          on_log=lambda step, m: resumed.append((step, m["train_loss"])))
    train(config, tiny_dataset, tmp_path / "resumed", resume=True, progress=False,
          on_log=lambda step, m: resumed.append((step, m["train_loss"])))
    assert [s for s, _ in straight] == [5, 10, 15, 20, 25, 30]
    assert resumed == straight  # every point, bit for bit


def test_stop_after_runs_the_start_of_the_whole_run_and_the_rate_probe_uses_it(tiny_dataset: Path,
                                                                               tmp_path: Path) -> None:
    config = load_config(None, QUICK + ["train.steps=30", "train.checkpoint_every=7"])
    straight = train(config, tiny_dataset, tmp_path / "straight", progress=False)
    start = train(config, tiny_dataset, tmp_path / "start", progress=False, stop_after=9)
    assert start.final_step == 9 and start.losses == straight.losses[:9]  # the run's own schedule and batches
    rest = train(config, tiny_dataset, tmp_path / "start", resume=True, progress=False)
    assert rest.final_step == 30 and start.losses + rest.losses == straight.losses

    # a recompile's step (50x the others) counts as a typical one; varying batch sizes still average
    assert steady_rate([0.1] * 19 + [5.0]) == pytest.approx(10.0)
    assert steady_rate([0.1, 0.2, 0.3]) == pytest.approx(3 / 0.6)
    rate = measure_step_rate(config, tiny_dataset, steps=6, warm_up=2)
    assert rate.steps_per_second > 0 and rate.settings == "fp32" and rate.measured_steps == 6
    assert rate.seconds_for(30) == pytest.approx(30 / rate.steps_per_second)
    with pytest.raises(ValueError, match="the run has 30 steps, fewer than the 31 to measure"):
        measure_step_rate(config, tiny_dataset, steps=30, warm_up=1)


def test_a_branch_from_a_kept_checkpoint_goes_on_as_the_trunk_did_until_its_anneal(tiny_dataset: Path,
                                                                                    tmp_path: Path) -> None:
    """`train.keep_checkpoints` keeps each curve point's checkpoint; a run started from one (`train.init_from`)
    continues the trunk's steps, rate and training clock bit for bit, and an anneal over its last steps changes
    only those; one may also draw held-still windows the trunk did not. A branch that changes anything else is
    refused."""
    trunk_config = load_config(None, QUICK + ["train.steps=20", "train.eval_every=10", "train.keep_checkpoints=true"])
    trunk = train(trunk_config, tiny_dataset, tmp_path / "trunk", progress=False, on_eval=lambda *args: None)
    kept = tmp_path / "trunk" / "checkpoint-10.pt"
    assert kept.is_file() and (tmp_path / "trunk" / "checkpoint-20.pt").is_file()
    branch = train(load_config(None, QUICK + ["train.steps=20", f"train.init_from={kept}"]), tiny_dataset,
                   tmp_path / "branch", progress=False)
    assert branch.start_step == 10 and branch.losses == trunk.losses[10:]  # bit for bit
    assert branch.wall_time_s > load_checkpoint(kept)["wall_time_s"] > 0  # the trunk's training time counts
    annealed = train(load_config(None, QUICK + ["train.steps=20", f"train.init_from={kept}",
                                                "train.learning_rate_anneal_steps=5"]),
                     tiny_dataset, tmp_path / "annealed", progress=False)
    assert annealed.losses[:6] == trunk.losses[10:16] and annealed.losses[6:] != trunk.losses[16:]
    held = train(load_config(None, QUICK + ["train.steps=20", f"train.init_from={kept}", "train.held_share=0.5"]),
                 tiny_dataset, tmp_path / "held", progress=False)
    assert held.start_step == 10 and held.losses != trunk.losses[10:]  # other windows drawn from the same state
    with pytest.raises(ValueError, match="noise_std"):
        train(load_config(None, QUICK + ["train.steps=20", f"train.init_from={kept}", "train.noise_std=1e-3"]),
              tiny_dataset, tmp_path / "other", progress=False)


def test_resume_refuses_a_different_model(tiny_dataset: Path, tmp_path: Path) -> None:
    train(load_config(None, QUICK + ["train.steps=2"]), tiny_dataset, tmp_path / "run", progress=False)
    with pytest.raises(FileExistsError, match="resume"):
        train(load_config(None, QUICK + ["train.steps=4"]), tiny_dataset, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="model config differs"):
        train(load_config(None, QUICK + ["train.steps=4", "model.latent_size=32"]), tiny_dataset,
              tmp_path / "run", resume=True, progress=False)


def test_bf16_training_tracks_fp32(tiny_dataset: Path, tmp_path: Path) -> None:
    runs = {}
    for precision in ("fp32", "bf16"):
        config = load_config(None, QUICK + ["train.steps=5", f"train.precision={precision}"])
        runs[precision] = train(config, tiny_dataset, tmp_path / precision, progress=False).losses
    assert runs["fp32"] != runs["bf16"]  # bf16 really ran
    first_fp32, first_bf16 = runs["fp32"][0], runs["bf16"][0]
    assert abs(first_bf16 - first_fp32) / first_fp32 < 0.05


@pytest.mark.slow  # inductor compiles for about a minute
def test_compiled_training_tracks_eager_and_checkpoints_load_eagerly(tiny_dataset: Path, tmp_path: Path) -> None:
    from torch._dynamo.utils import counters

    runs = {}
    for compiled in (False, True):
        counters.clear()
        config = load_config(None, QUICK + ["train.steps=5", f"train.compile={str(compiled).lower()}"])
        runs[compiled] = train(config, tiny_dataset, tmp_path / str(compiled), progress=False)
        assert (counters["stats"]["unique_graphs"] > 0) == compiled  # dynamo really traced the network
    eager, compiled = runs[False].losses, runs[True].losses
    np.testing.assert_allclose(compiled, eager, rtol=1e-3)  # the same function, fused differently
    simulator, _, _ = load_simulator(runs[True].checkpoint)  # parameter names unchanged by compiling
    reference, _, _ = load_simulator(runs[False].checkpoint)
    assert simulator.state_dict().keys() == reference.state_dict().keys()


def test_training_noise_leaves_kinematic_particles_alone(tiny_dataset: Path) -> None:
    """The noise the loop trains with (`step_inputs`) is zero on kinematic rows, which follow the data, and
    random-walk noise on the others; its moving count is the whole batch's."""
    from gns_bench.data.windows import WindowSampler
    from gns_bench.train.loop import step_inputs

    sampler = WindowSampler(load_split(tiny_dataset, "train"), 6, seed=0)
    batch, noise, num_moving = step_inputs(sampler, step=3, batch_size=2, noise_std=3e-4)
    kinematic = (batch.particle_type == 3).numpy()
    assert kinematic.any() and num_moving == int((~kinematic).sum())
    assert not noise[kinematic].any()
    assert (noise[~kinematic][:, 1:].abs() > 0).all()  # every moving row noised after the first position


def test_time_budget_and_curve_evaluation(tiny_dataset: Path, tmp_path: Path) -> None:
    """`train.max_wall_seconds` stops training by time; `train.eval_every` evaluates along the way on the
    validation subset, and that time is not training time."""
    from gns_bench.train.loop import train

    config = load_config(None, QUICK + ["train.steps=1000000", "train.max_wall_seconds=3", "train.eval_every=5"])
    points: list[tuple[int, float]] = []

    def on_eval(simulator, step: int, seconds: float) -> None:
        assert not simulator.training
        points.append((step, seconds))
        import time
        time.sleep(0.5)  # evaluation time must not count against the budget

    result = train(config, tiny_dataset, tmp_path / "run", progress=False, on_eval=on_eval)
    assert 0 < result.final_step < 1000000
    assert 3.0 <= result.wall_time_s < 3.0 + 5.0  # stops at the first step past the budget
    assert result.eval_seconds >= 0.5 * len(points)
    steps = [s for s, _ in points]
    assert steps[0] == 0 and steps[1:-1] == list(range(5, 5 * (len(steps) - 1), 5))[: len(steps) - 2]
    assert steps[-1] == result.final_step
    seconds = [t for _, t in points]
    assert seconds == sorted(seconds) and seconds[-1] <= result.wall_time_s + 1e-6


def test_a_curve_point_cut_short_by_a_stop_is_evaluated_on_resume(tiny_dataset: Path, tmp_path: Path) -> None:
    """The checkpoint at a curve step is written before its evaluation: a run stopped during that evaluation
    resumes at the step and evaluates it then, the last step's point included (nothing is left to train)."""
    from gns_bench.train.loop import train

    config = load_config(None, QUICK + ["train.steps=20", "train.eval_every=10"])
    points: list[int] = []

    def stopped_at(when: int):
        def on_eval(simulator, step: int, seconds: float) -> None:
            if step == when and -when not in points:
                points.append(-step)  # begun, not logged
                raise KeyboardInterrupt
            points.append(step)
        return on_eval

    for when in (10, 20):
        points.clear()
        out = tmp_path / f"stop{when}"
        with pytest.raises(KeyboardInterrupt):
            train(config, tiny_dataset, out, progress=False, on_eval=stopped_at(when))
        train(config, tiny_dataset, out, resume=True, progress=False, on_eval=stopped_at(when))
        assert [p for p in points if p >= 0] == [0, 10, 20], (when, points)
        train(config, tiny_dataset, out, resume=True, progress=False, on_eval=stopped_at(when))
        assert [p for p in points if p >= 0] == [0, 10, 20], (when, points)  # a finished run evaluates nothing


def test_step_clock_counts_a_stall_as_a_few_typical_steps() -> None:
    """A run stopped with SIGSTOP mid-step (or stalled by another job) must not spend its time budget."""
    from gns_bench.train.loop import StepClock

    clock = StepClock(earlier=100.0)
    for _ in range(20):
        clock.add(0.5)
    assert clock.total == pytest.approx(110.0)
    assert clock.add(600.0) == pytest.approx(1.5)  # a ten-minute pause counts as 3 x the median step
    assert clock.total == pytest.approx(111.5)
    first = StepClock()
    assert first.add(60.0) == 60.0  # warm-up steps (compilation) count in full


def test_threads_stay_within_the_usable_cores_and_oversubscription_is_said(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    from gns_bench import devices
    from gns_bench.train import loop

    before = torch.get_num_threads()
    try:
        monkeypatch.setattr(devices, "usable_cores", lambda: 1)
        assert devices.set_threads(8) == 1 and torch.get_num_threads() == 1  # asked for more than it may use
        assert devices.set_threads(None) == 1
    finally:
        torch.set_num_threads(before)
    monkeypatch.setattr(loop, "usable_cores", lambda: 2)
    loads = iter([1.9, 5.3, 2.1])
    monkeypatch.setattr(loop, "load_average", lambda: next(loads))
    watch = loop.LoadWatch(own_threads=2)
    with pytest.warns(UserWarning, match="oversubscribed: load 5.3 on 2 usable cores"):
        for _ in range(3):
            watch.sample()
    assert watch.report() == "load above 2.5 (2 cores) at 1 of 3 logged steps, up to 5.3"
    assert loop.LoadWatch(own_threads=2).report() == ""


def test_start_window_share_draws_from_the_start_and_leaves_the_release_sampler_alone(tiny_dataset: Path) -> None:
    """`train.start_window_share`: a share 0 draws exactly the release's uniform windows; share 1 only windows
    among the first `start_windows` of a trajectory; a share in between about that share of them."""
    from gns_bench.data.windows import WindowSampler

    trajectories = load_split(tiny_dataset, "train")
    uniform = WindowSampler(trajectories, 6, seed=3)
    zero = WindowSampler(trajectories, 6, seed=3, start_share=0.0, start_windows=4)
    assert all(uniform.samples(step, 8) == zero.samples(step, 8) for step in range(20))
    early = WindowSampler(trajectories, 6, seed=3, start_share=1.0, start_windows=4)
    frames = [t for step in range(50) for _, t in early.samples(step, 8)]
    assert min(frames) == 5 and max(frames) == 8  # last input frames 5 .. 5 + 4 - 1
    half = WindowSampler(trajectories, 6, seed=3, start_share=0.5, start_windows=4)
    share = np.mean([t <= 8 for step in range(200) for _, t in half.samples(step, 8)])
    uniform_share = 4 / (trajectories[0].num_steps - 6)  # what uniform draws put there by chance
    assert 0.5 < share < 0.5 + uniform_share + 0.08
    with pytest.raises(ValueError, match="start_share"):
        WindowSampler(trajectories, 6, seed=3, start_share=1.5)


def test_held_share_replaces_that_share_of_windows_with_blocks_let_go_from_rest(tiny_dataset: Path) -> None:
    """`train.held_share`: a share 0 draws the release's windows from the training trajectories themselves;
    a share 0.5 replaces about half the samples (the others as they were) by windows at rest whose target is
    the fall from rest at g, taken at frames where every moving particle of the truth is in free fall."""
    from gns_bench.data.free_fall import falling_frames
    from gns_bench.data.windows import WindowSampler

    trajectories, gravity = load_split(tiny_dataset, "train"), read_metadata(tiny_dataset).gravity
    frames = [falling_frames(traj, gravity) for traj in trajectories]
    assert sum(len(f) for f in frames) > 0  # the tiny domain's blocks fall before they land
    uniform = WindowSampler(trajectories, 6, seed=3)
    zero = WindowSampler(trajectories, 6, seed=3, held_share=0.0, held_frames=frames, gravity=gravity)
    assert all(zero.draw(step, 8) == (trajectories, uniform.samples(step, 8)) for step in range(10))
    half = WindowSampler(trajectories, 6, seed=3, held_share=0.5, held_frames=frames, gravity=gravity)
    held, released = 0, []
    for step in range(50):
        drawn, samples = half.draw(step, 8)
        for slot, (index, t) in enumerate(samples):
            if index < len(trajectories):
                assert (index, t) == uniform.samples(step, 8)[slot]
                continue
            held += 1
            released.append(t - 5)
            path = drawn[index].position  # held for 6 frames, then falling from rest: p + g m (m + 1) / 2
            moving = drawn[index].particle_type != KINEMATIC_PARTICLE_TYPE
            for f in range(t + 2):  # the window and its target
                m = max(0, f - 5)
                assert np.allclose(path[f][moving], path[0][moving] + np.multiply(gravity, m * (m + 1) / 2),
                                   rtol=0, atol=1e-7)  # float32 positions
    assert 0.35 < held / 400 < 0.65
    assert set(released) == set(range(6))  # from every input velocity 0 to a window all of the fall
    drawn, samples = half.draw(0, 8)
    assert half.batch(0, 8).window.shape[0] == sum(drawn[i].num_particles for i, _ in samples)
    with pytest.raises(ValueError, match="gravity"):
        WindowSampler(trajectories, 6, seed=3, held_share=0.5, held_frames=frames, gravity=None)
    with pytest.raises(ValueError, match="free fall"):
        WindowSampler(trajectories, 6, seed=3, held_share=0.5, held_frames=[f[:0] for f in frames], gravity=gravity)


def test_training_with_held_still_windows_runs_and_refuses_a_dataset_without_gravity(tiny_dataset: Path,
                                                                                     tmp_path: Path) -> None:
    result = train(load_config(None, QUICK + ["train.steps=20", "train.held_share=0.25"]), tiny_dataset,
                   tmp_path / "run", progress=False)
    assert result.final_step == 20 and np.isfinite(result.losses).all()
    no_gravity = tmp_path / "no-gravity"
    shutil.copytree(tiny_dataset, no_gravity)
    meta = json.loads((no_gravity / "metadata.json").read_text())
    meta.pop("gravity")
    (no_gravity / "metadata.json").write_text(json.dumps(meta))
    assert read_metadata(no_gravity).gravity is None
    with pytest.raises(ConfigError, match="no `gravity`"):
        train(load_config(None, QUICK + ["train.steps=5", "train.held_share=0.25"]), no_gravity,
              tmp_path / "refused", progress=False)


def test_warm_up_ramps_the_rate_linearly_then_the_decay_goes_on() -> None:
    config = load_config(None, ["train.learning_rate_warmup_steps=100"]).train
    assert learning_rate(0, config) == pytest.approx(1e-6)  # a hundredth of the 1e-4 peak
    assert learning_rate(49, config) == pytest.approx(0.5 * learning_rate(49, load_config().train))
    assert learning_rate(100, config) == learning_rate(100, load_config().train)


def test_the_anneal_falls_linearly_over_the_last_steps_from_where_the_schedule_stood() -> None:
    plain = load_config(None, ["train.steps=1000", "train.learning_rate_final=1e-4"]).train  # constant 1e-4
    wsd = load_config(None, ["train.steps=1000", "train.learning_rate_final=1e-4",
                             "train.learning_rate_anneal_steps=200", "train.learning_rate_anneal_to=1e-6"]).train
    assert [learning_rate(s, wsd) for s in (0, 799, 800)] == [1e-4] * 3  # stable up to the anneal's start
    assert learning_rate(900, wsd) == pytest.approx(0.5 * (1e-4 + 1e-6))  # half-way down
    assert learning_rate(1000, wsd) == pytest.approx(1e-6) and learning_rate(999, plain) == 1e-4
    decaying = load_config(None, ["train.steps=1000", "train.learning_rate_anneal_steps=200"]).train
    assert learning_rate(800, decaying) == pytest.approx(learning_rate(800, load_config().train))  # where it stood
    with pytest.raises(ConfigError, match="learning_rate_anneal_steps"):
        load_config(None, ["train.steps=100", "train.learning_rate_anneal_steps=200"])


def test_pushforward_trains_from_the_models_own_window_against_the_truth(tiny_dataset: Path) -> None:
    """`train.pushforward_*`: off, or before its start, no step unrolls; on, a share of steps unrolls 1..U steps
    (the same for a resumed run); the loss of an unrolled step is the one-step loss on the window the model's own
    predictions made, its target corrected for the window's drift from the truth as the noise correction is:
    the true next velocity from where the window stands (`train.position_correction` 0, the paper's default),
    or the true next position (1)."""
    import torch

    from gns_bench.data.format import read_metadata
    from gns_bench.data.windows import WindowSampler
    from gns_bench.model.features import acceleration_from_next_position
    from gns_bench.model.noise import noisy_training_pair
    from gns_bench.model.simulator import kinematic_mask
    from gns_bench.train.checkpoints import build_simulator
    from gns_bench.train.loop import pushforward_unroll, step_inputs, training_loss

    off = load_config().train
    assert all(pushforward_unroll(off, step) == 0 for step in range(200))
    on = load_config(None, ["train.pushforward_steps=3", "train.pushforward_start=100",
                            "train.pushforward_share=0.5"]).train
    draws = [pushforward_unroll(on, step) for step in range(100, 1100)]
    assert all(pushforward_unroll(on, step) == 0 for step in range(100))
    assert set(draws) == {0, 1, 2, 3} and 0.4 < np.mean([d > 0 for d in draws]) < 0.6
    assert draws == [pushforward_unroll(on, step) for step in range(100, 1100)]  # drawn from seed and step alone

    config = load_config(None, ["model.message_passing_steps=1", "model.latent_size=16", "model.mlp_hidden_size=16",
                                "train.pushforward_steps=2"])
    trajectories = load_split(tiny_dataset, "train")
    torch.manual_seed(0)
    simulator = build_simulator(config, read_metadata(tiny_dataset))
    sampler = WindowSampler(trajectories, 6, seed=0, future=3)
    batch, noise, moving = step_inputs(sampler, 0, 2, 3e-4)
    assert batch.future.shape[1] == 3
    window, _ = noisy_training_pair(batch.window, batch.target, noise, 0.0)
    kinematic = kinematic_mask(batch.particle_type)
    with torch.no_grad():  # two steps by hand, kinematic particles on their true paths
        for k in range(2):
            nxt = simulator.predict_next_position(window, batch.particle_type, batch.batch)
            nxt[kinematic] = batch.future[kinematic, k]
            window = torch.cat([window[:, 1:], nxt[:, None]], dim=1)
        velocity_target = window[:, -1] + batch.future[:, 2] - batch.future[:, 1]  # the true next velocity
        prediction = simulator(window, batch.particle_type, batch.batch)
        for correction, target_next in ((0.0, velocity_target), (1.0, batch.future[:, 2])):
            target = simulator.normalise_acceleration(acceleration_from_next_position(window, target_next))
            error = (prediction - target).square().sum(-1)
            expected = error[~kinematic].sum() / moving
            got = training_loss(simulator, batch, noise, correction, num_moving=moving, unroll=2)
            assert float(got) == pytest.approx(float(expected), rel=1e-5), correction
        plain = training_loss(simulator, batch, noise, 0.0, num_moving=moving)
    assert float(got) != pytest.approx(float(plain), rel=1e-3)  # the unrolled step trains on something else
