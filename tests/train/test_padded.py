"""Training steps on padded graphs (gns_bench/train/padded.py): the loss and every gradient of the paper's loss
on the real particles, whatever the padding; the buckets' sizes; the refusal of the global-latent ablation."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gns_bench.config import load_config
from gns_bench.data.format import load_split, read_metadata
from gns_bench.data.windows import WindowSampler
from gns_bench.train.checkpoints import build_simulator
from gns_bench.train.loop import step_inputs
from gns_bench.train.losses import training_loss
from gns_bench.train.padded import bucket, pad_batch, padded_loss


def test_buckets_leave_a_pad_row_and_grow_by_a_quarter() -> None:
    sizes = range(0, 20_000, 7)
    assert all(bucket(s) > s for s in sizes)
    assert all(bucket(s) <= max(256, 1.25 * s + 64) * 1.25 for s in sizes)  # at most a quarter of waste, and a step
    assert len({bucket(s) for s in range(1_000, 2_000)}) <= 4  # a 1,000-2,000 particle dataset: a few graphs
    assert bucket(255) == 256 and bucket(256) == 320
    with pytest.raises(ValueError, match="at least 0"):
        bucket(-1)


def _simulator_and_step(tiny_dataset: Path, overrides: list[str] | None = None):
    config = load_config(None, ["model.latent_size=16", "model.mlp_hidden_size=16", "model.message_passing_steps=2",
                                *(overrides or [])])
    torch.manual_seed(0)
    simulator = build_simulator(config, read_metadata(tiny_dataset))
    sampler = WindowSampler(load_split(tiny_dataset, "train"), 6, seed=0)
    return simulator, step_inputs(sampler, step=3, batch_size=2, noise_std=3e-4)


def _gradients(simulator, loss: torch.Tensor) -> dict[str, torch.Tensor]:
    simulator.zero_grad(set_to_none=True)
    loss.backward()
    return {name: p.grad.clone() for name, p in simulator.named_parameters() if p.grad is not None}


@pytest.mark.parametrize("extra_nodes, extra_edges", [(1, 0), (300, 5_000)])
def test_a_padded_step_takes_the_loss_and_gradients_of_the_unpadded_one(tiny_dataset: Path, extra_nodes: int,
                                                                        extra_edges: int) -> None:
    """Pad rows in a graph of their own, pad edges among themselves, pad and kinematic rows weighed 0: the
    padded loss and each parameter's gradient are the release's loss on the real batch (Sec. 4.3, App. B.1)."""
    simulator, (batch, noise, num_moving) = _simulator_and_step(tiny_dataset)
    kinematic = batch.particle_type == 3
    assert kinematic.any()  # the tiny domain has them: the weights must leave them out
    expected = training_loss(simulator, batch, noise, 0.0, num_moving=num_moving)
    expected_grads = _gradients(simulator, expected)
    n = batch.window.shape[0]
    edges = simulator.build_graph((batch.window + noise)[:, -1], batch.batch).shape[1]
    padded = pad_batch(simulator, batch, noise, 0.0, nodes=n + extra_nodes, edges=edges + extra_edges)
    assert padded.shape == (n + extra_nodes, edges + extra_edges)
    loss = padded_loss(simulator, padded)
    assert float(loss) == pytest.approx(float(expected), rel=1e-5)
    grads = _gradients(simulator, loss)
    assert grads.keys() == expected_grads.keys()
    for name, grad in grads.items():
        scale = float(expected_grads[name].abs().max()) or 1.0
        assert float((grad - expected_grads[name]).abs().max()) <= 1e-4 * scale, name


def test_a_batch_that_does_not_fit_its_padding_and_the_global_latent_are_refused(tiny_dataset: Path) -> None:
    simulator, (batch, noise, _) = _simulator_and_step(tiny_dataset)
    with pytest.raises(ValueError, match="do not fit"):
        pad_batch(simulator, batch, noise, 0.0, nodes=batch.window.shape[0])  # no pad row left
    simulator, (batch, noise, _) = _simulator_and_step(tiny_dataset, ["model.global_latent=true"])
    with pytest.raises(ValueError, match="global_latent"):
        pad_batch(simulator, batch, noise, 0.0)


def test_adams_state_is_given_before_a_capture_without_a_training_step() -> None:
    """`give_state` (run before a CUDA graph captures the first step): the weights do not move, and the steps
    after it are those of an optimiser that never had it, bias correction included."""
    from gns_bench.train.padded import give_state, set_learning_rate

    torch.manual_seed(0)
    start = torch.nn.Linear(4, 3)
    grads = [torch.randn(3, 4) for _ in range(3)]
    runs = []
    for given in (False, True):
        layer = torch.nn.Linear(4, 3)
        layer.load_state_dict(start.state_dict())
        optimiser = torch.optim.Adam(layer.parameters(), lr=torch.tensor(1e-2))
        if given:
            give_state(optimiser)
            assert torch.equal(layer.weight, start.weight) and torch.equal(layer.bias, start.bias)
        for i, grad in enumerate(grads):
            set_learning_rate(optimiser, 1e-2 / (i + 1))  # written into the rate's tensor
            layer.weight.grad, layer.bias.grad = grad.clone(), grad[:, 0].clone()
            optimiser.step()
        assert isinstance(optimiser.param_groups[0]["lr"], torch.Tensor)
        runs.append(layer.weight.detach().clone())
    assert torch.equal(runs[0], runs[1])
