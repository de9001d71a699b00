"""The CUDA paths (issue #22): the same model, neighbours and training on a GPU as on the CPU. Skipped where
torch sees no GPU (CI); `nox -s device` runs them on a lent one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gns_bench.config import ModelConfig
from gns_bench.data.format import read_metadata
from gns_bench.model.neighbours import radius_graph
from gns_bench.model.simulator import LearnedSimulator

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")]


def _window(n: int = 300, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    start = torch.rand(n, 1, 2, generator=g) * 0.5 + 0.25
    velocity = torch.randn(n, 1, 2, generator=g) * 1e-3
    steps = torch.arange(6, dtype=torch.float32)[None, :, None]
    return start + steps * velocity, torch.zeros(n, dtype=torch.long)


def test_radius_graph_on_the_gpu_finds_the_cpus_edges() -> None:
    positions = _window(2000)[0][:, -1]
    cpu = radius_graph(positions, 0.03, backend="cell_list")
    gpu = radius_graph(positions.cuda(), 0.03, backend="cell_list")
    assert gpu.device.type == "cuda" and cpu.shape[1] > 2000
    assert torch.equal(gpu.cpu(), cpu)


def test_the_simulator_predicts_the_same_on_the_gpu(tiny_dataset: Path) -> None:
    meta = read_metadata(tiny_dataset)
    torch.manual_seed(0)
    config = ModelConfig(latent_size=32, mlp_hidden_size=32, message_passing_steps=3,
                         connectivity_radius=meta.default_connectivity_radius)
    simulator = LearnedSimulator(config, meta, 3e-4).eval()
    window, types = _window(200)
    with torch.no_grad():
        cpu = simulator.predict_next_position(window, types)
        gpu = simulator.cuda().predict_next_position(window.cuda(), types.cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-6)


def test_training_on_the_gpu_learns_and_beats_constant_velocity(tiny_dataset: Path, tmp_path: Path) -> None:
    from gns_bench.config import load_config
    from gns_bench.data.format import load_split
    from gns_bench.evaluate.evaluate import evaluate
    from gns_bench.train.checkpoints import load_simulator
    from gns_bench.train.loop import train

    quick = ["model.message_passing_steps=2", "model.latent_size=64", "model.mlp_hidden_size=64",
             "train.batch_size=8", "train.learning_rate=2e-3", "train.learning_rate_decay_steps=2000",
             "train.noise_std=1e-5", "train.log_every=50", "train.steps=1200", "train.device=cuda"]
    result = train(load_config(None, quick), tiny_dataset, tmp_path / "run", progress=False)
    assert np.mean(result.losses[-100:]) < np.mean(result.losses[:20]) / 10
    simulator, config, _ = load_simulator(result.checkpoint, device="cuda")
    m = evaluate(simulator, load_split(tiny_dataset, "test"), config.eval, device="cuda", progress=False).metrics
    assert m["rollout_mse"] < 0.1 * m["baseline_cv_rollout_mse"], m


@pytest.mark.parametrize("architecture", ["cconv", "dpi"])
def test_a_baseline_trains_on_the_gpu_and_measures_as_on_the_cpu(architecture: str, tiny_dataset: Path,
                                                                 tmp_path: Path) -> None:
    """The paper's baselines (Sec. 5.5) through the same loop on CUDA: the trained network, moved to the CPU,
    gives the same one-step and short-rollout errors as on the GPU."""
    from gns_bench.config import load_config
    from gns_bench.data.format import load_split
    from gns_bench.evaluate.evaluate import evaluate
    from gns_bench.train.checkpoints import load_simulator
    from gns_bench.train.loop import train

    overrides = [f"model.architecture={architecture}", "train.steps=40", "train.log_every=20", "train.device=cuda",
                 "eval.max_trajectories=1", "eval.rollout_steps=5", "eval.one_step_windows=5"]
    result = train(load_config(None, overrides), tiny_dataset, tmp_path / "run", progress=False)
    assert np.isfinite(result.losses).all() and len(result.losses) > 0
    test = load_split(tiny_dataset, "test")
    metrics = {}
    for device in ("cuda", "cpu"):
        simulator, config, _ = load_simulator(result.checkpoint, device=device)
        assert next(simulator.parameters()).device.type == device
        metrics[device] = evaluate(simulator, test, config.eval, device=device, progress=False).metrics
    gpu, cpu = metrics["cuda"], metrics["cpu"]
    assert np.isfinite(gpu["one_step_mse"]) and np.isfinite(gpu["rollout_mse"])
    np.testing.assert_allclose(gpu["one_step_mse"], cpu["one_step_mse"], rtol=1e-3)
    np.testing.assert_allclose(gpu["rollout_mse"], cpu["rollout_mse"], rtol=1e-2)


def test_captured_training_steps_follow_the_eager_ones(tiny_dataset: Path) -> None:
    """CUDA graphs over padded buckets (gns_bench/train/padded.py): steps replayed from captured graphs, over two
    bucket shapes taken in turn and a rate that changes every step, give the losses and weights of the same
    padded steps run eagerly with a plain Adam (up to the GPU's scatter-add rounding)."""
    from gns_bench.config import load_config
    from gns_bench.data.format import load_split
    from gns_bench.data.windows import WindowSampler
    from gns_bench.train.checkpoints import build_simulator
    from gns_bench.train.loop import step_inputs
    from gns_bench.train.padded import GraphedSteps, capturable_adam, pad_batch, padded_loss, set_learning_rate

    config = load_config(None, ["model.latent_size=32", "model.mlp_hidden_size=32"])
    meta = read_metadata(tiny_dataset)
    torch.manual_seed(0)
    eager = build_simulator(config, meta).cuda()
    graphed = build_simulator(config, meta).cuda()
    graphed.load_state_dict(eager.state_dict())
    plain = torch.optim.Adam(eager.parameters(), lr=1e-3)
    captured = GraphedSteps(graphed, capturable_adam(graphed.parameters(), 1e-3))
    sampler = WindowSampler(load_split(tiny_dataset, "train"), 6, seed=0)
    shapes = [(128, 2_048), (192, 3_072)]
    for step in range(6):
        batch, noise, num_moving = step_inputs(sampler, step, 2, 3e-4)
        lr = 1e-3 * (1 - step / 10)
        nodes, edges = shapes[step % 2]
        padded = pad_batch(eager, batch.to("cuda"), noise.cuda(), 0.0, nodes=nodes, edges=edges,
                           num_moving=num_moving)
        set_learning_rate(plain, lr)
        loss = padded_loss(eager, padded)
        plain.zero_grad(set_to_none=True)
        loss.backward()
        plain.step()
        set_learning_rate(captured.optimiser, lr)
        replayed = captured.step(padded)
        assert float(replayed) == pytest.approx(float(loss), rel=1e-4), step
    assert len(captured.graphs) == 2
    for (name, ours), theirs in zip(graphed.named_parameters(), eager.parameters(), strict=True):
        assert torch.allclose(ours, theirs, rtol=1e-4, atol=1e-6), name
