"""The weights' moving average (`train.weight_average`): its arithmetic, and a run trained with it tested as it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gns_bench.config import ConfigError, load_config
from gns_bench.train.averaging import WeightAverage, averaged, effective_decay
from gns_bench.train.checkpoints import load_checkpoint, load_simulator
from gns_bench.train.loop import train

QUICK = ["model.message_passing_steps=2", "model.latent_size=64", "model.mlp_hidden_size=64",
         "train.batch_size=8", "train.learning_rate=2e-3", "train.learning_rate_decay_steps=2000",
         "train.noise_std=1e-5", "train.log_every=50"]


def scalar_module(value: float, dtype: torch.dtype = torch.float32) -> torch.nn.Module:
    module = torch.nn.Module()
    module.w = torch.nn.Parameter(torch.tensor([value], dtype=dtype))
    module.register_buffer("stats", torch.tensor([7.0]))
    return module


def test_the_average_follows_its_closed_forms() -> None:
    module = scalar_module(2.0)
    average = WeightAverage(module, decay=0.9)
    module.w.data.fill_(12.0)
    average.update()  # the first update keeps a tenth of the start: 0.1 * 2 + 0.9 * 12
    assert average.values[0].item() == pytest.approx(11.0)
    assert [effective_decay(0.9, n) for n in (0, 8, 80, 10_000)] == pytest.approx([0.1, 0.5, 0.9, 0.9])
    # weights that alternate +-1 about their mean leave an average that alternates +-(1 - d) / (1 + d)
    for n in range(400):
        module.w.data.fill_(1.0 if n % 2 == 0 else -1.0)
        average.update()
    assert abs(average.values[0].item()) == pytest.approx((1 - 0.9) / (1 + 0.9), rel=1e-4)
    # held weights: the average comes to them and stays
    module.w.data.fill_(3.0)
    for _ in range(300):
        average.update()
    assert average.values[0].item() == pytest.approx(3.0, abs=1e-6)
    with pytest.raises(ValueError, match="decay"):
        WeightAverage(module, decay=1.0)


def test_the_averaged_state_keeps_buffers_and_dtypes_and_refuses_another_models() -> None:
    module = scalar_module(1.0, torch.bfloat16)
    average = WeightAverage(module, decay=0.5)
    assert average.values[0].dtype == torch.float32  # averaged in float32 whatever the weights' type
    module.w.data.fill_(3.0)
    average.update()
    state = averaged(module.state_dict(), average.state_dict())
    assert state["w"].dtype == torch.bfloat16 and state["w"].item() == pytest.approx(0.1 * 1.0 + 0.9 * 3.0, rel=1e-2)
    assert state["stats"].item() == 7.0  # buffers are the model's
    assert averaged(module.state_dict(), None)["w"].item() == 3.0
    with pytest.raises(ValueError, match="not the model's"):
        averaged({"other": torch.zeros(1)}, average.state_dict())
    with pytest.raises(ConfigError, match="weight_average"):
        load_config(None, ["train.weight_average=1.0"])


def test_a_run_with_an_average_is_tested_evaluated_and_resumed_with_it(tiny_dataset: Path, tmp_path: Path) -> None:
    """The checkpoint keeps the weights (to resume) and their average; the run's model (`load_simulator`) and its
    curve points are the average; a resumed run's average is the uninterrupted run's bit for bit."""
    config = load_config(None, QUICK + ["train.steps=30", "train.checkpoint_every=7", "train.weight_average=0.9",
                                        "train.eval_every=10"])
    seen: list[dict[str, torch.Tensor]] = []
    straight = train(config, tiny_dataset, tmp_path / "straight", progress=False,
                     on_eval=lambda simulator, step, seconds: seen.append(
                         {k: v.clone() for k, v in simulator.state_dict().items()}))
    saved = load_checkpoint(straight.checkpoint)
    raw, mean = saved["model"], saved["average"]["values"]
    assert saved["average"]["updates"] == 30 and set(mean) <= set(raw)
    assert any(not torch.equal(raw[name], mean[name]) for name in mean)  # the average is not the last weights
    simulator, _, _ = load_simulator(straight.checkpoint)
    loaded = simulator.state_dict()
    assert all(torch.equal(loaded[name], mean[name]) for name in mean)
    assert all(torch.equal(seen[-1][name], mean[name]) for name in mean)  # the last curve point: the average

    first_half = load_config(None, QUICK + ["train.steps=13", "train.checkpoint_every=7", "train.weight_average=0.9"])
    train(first_half, tiny_dataset, tmp_path / "resumed", progress=False)
    rest = load_config(None, QUICK + ["train.steps=30", "train.checkpoint_every=7", "train.weight_average=0.9"])
    resumed = load_checkpoint(train(rest, tiny_dataset, tmp_path / "resumed", resume=True, progress=False).checkpoint)
    assert resumed["average"]["updates"] == 30
    assert all(torch.equal(resumed["average"]["values"][name], mean[name]) for name in mean)  # bit for bit


def test_a_branch_may_start_an_average_its_trunk_did_not_keep(tiny_dataset: Path, tmp_path: Path) -> None:
    trunk = load_config(None, QUICK + ["train.steps=10", "train.eval_every=10", "train.keep_checkpoints=true"])
    train(trunk, tiny_dataset, tmp_path / "trunk", progress=False, on_eval=lambda *args: None)
    kept = tmp_path / "trunk" / "checkpoint-10.pt"
    assert "average" not in load_checkpoint(kept)
    branch = load_config(None, QUICK + ["train.steps=11", f"train.init_from={kept}", "train.weight_average=0.999"])
    saved = load_checkpoint(train(branch, tiny_dataset, tmp_path / "branch", progress=False).checkpoint)
    start, now = load_checkpoint(kept)["model"], saved["model"]
    assert saved["average"]["updates"] == 1  # one step from the trunk's weights: a tenth of them kept
    for name, value in saved["average"]["values"].items():
        torch.testing.assert_close(value, 0.1 * start[name] + 0.9 * now[name], rtol=1e-6, atol=1e-7)
