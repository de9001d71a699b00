"""The timed side-by-side with geoelements/gns (gns_bench/bench/peer_speed.py): interleaved timing, paired
ratios, the targets, and gns-bench's training iteration; with a geoelements/gns checkout named by GNS_BENCH_GEO,
that both codes' iterations compute the same loss on the same weights and batch."""

from __future__ import annotations

import os

import pytest
import torch

from gns_bench.bench import peer_speed
from gns_bench.bench.measure import batch_of
from gns_bench.config import ModelConfig

TINY = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2)


def test_variants_take_turns_within_each_repeat_after_an_untimed_warm_up() -> None:
    calls: list[str] = []
    ticks = iter(range(1000))
    times = peer_speed.interleaved({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, repeats=3,
                                   warmup=1, clock=lambda: float(next(ticks)))
    assert calls == ["a", "b"] * 4  # one warm-up round, then three timed ones, in turn
    assert times == {"a": [1.0, 1.0, 1.0], "b": [1.0, 1.0, 1.0]} and len(times["a"]) == 3


def test_a_ratio_pairs_each_repeat_so_a_drifting_host_cancels() -> None:
    """The host halves its speed after the first repeat: each repeat's ratio stays 2. A slow spell that lands on
    ours in one repeat and on the peer's in another moves one ratio each way, and the median stays 2 where the
    ratio of the medians would read 0.5."""
    peer, ours = [1.0, 2.0, 2.0], [0.5, 1.0, 1.0]
    assert peer_speed.paired_ratio(peer, ours) == 2.0
    spelled_peer, spelled_ours = [1.0, 1.0, 4.0], [0.5, 2.0, 2.0]
    assert peer_speed.paired_ratio(spelled_peer, spelled_ours) == 2.0
    assert peer_speed.paired_ratio([1.0, 2.0], [1.0, 1.0]) == 1.5


def test_targets_take_the_fastest_variant_of_each_precision() -> None:
    rows = [{"density": "d", "variant": "geoelements/gns fp32", "speed_up": 1.0},
            {"density": "d", "variant": "ours fp32 eager", "speed_up": 3.2},
            {"density": "d", "variant": "ours fp32 compiled", "speed_up": 2.5},
            {"density": "d", "variant": "ours bf16 eager", "speed_up": 4.0},
            {"density": "d", "variant": "ours bf16 compiled", "speed_up": 5.9}]
    verdicts = {v["precision"]: v for v in peer_speed.verdicts(rows)}
    assert verdicts["fp32"]["variant"] == "ours fp32 eager" and verdicts["fp32"]["met"]
    assert verdicts["bf16"]["variant"] == "ours bf16 compiled" and not verdicts["bf16"]["met"]  # 5.9 < 6


def test_our_iteration_trains_the_model_on_the_batch() -> None:
    batch, scene = batch_of(2, 150, 15.0)
    assert batch.window.shape == (300, 6, 2) and batch.batch.tolist() == [0] * 150 + [1] * 150
    iteration = peer_speed.ours_iteration(TINY, batch, scene, "fp32", compiled=False, noise_std=0.0)
    losses = [iteration() for _ in range(30)]
    assert all(torch.isfinite(torch.tensor(losses)))
    assert losses[-1] < 0.9 * losses[0]  # Adam steps on a fixed batch: the loss falls


@pytest.mark.skipif(not os.environ.get("GNS_BENCH_GEO"), reason="no geoelements/gns checkout (GNS_BENCH_GEO)")
def test_both_codes_compute_one_loss_on_the_same_weights_and_batch() -> None:
    """Like for like: with no noise drawn, the peer's first iteration and ours take the same loss."""
    from gns_bench.bench.peer import import_geo

    geo = import_geo(os.environ["GNS_BENCH_GEO"])
    batch, scene = batch_of(2, 150, 15.0)
    ours = peer_speed.ours_iteration(TINY, batch, scene, "fp32", compiled=False, noise_std=0.0)()
    theirs = peer_speed.peer_iteration(geo, TINY, batch, scene, noise_std=0.0)()
    assert theirs == pytest.approx(ours, rel=1e-4)


def test_the_bench_index_reads_the_side_by_side_and_the_graphed_rows(tmp_path) -> None:
    """A machine's folder with `peer_speed.json` and `graphed.json` gets one index line each
    (bench/report._extra_checks), with the targets' verdicts and the speed-ups over eager."""
    import json

    from gns_bench.bench.report import _extra_checks

    folder = tmp_path / "machine"
    folder.mkdir()
    rows = [{"density": "paper density", "variant": v, "speed_up": x} for v, x in
            (("geoelements/gns fp32", 1.0), ("ours fp32 eager", 3.5), ("ours bf16 compiled", 5.0))]
    (folder / "peer_speed.json").write_text(json.dumps(rows))
    (folder / "graphed.json").write_text(json.dumps(
        [{"batch": 2, "precision": "fp32", "stepping": "eager", "seconds": 0.02, "graphs_per_second": 100.0},
         {"batch": 2, "precision": "fp32", "stepping": "CUDA graph, padded", "seconds": 0.005,
          "graphs_per_second": 400.0}]))
    lines = _extra_checks(folder)
    peer = next(line for line in lines if "geoelements/gns" in line)
    assert "fp32 3.50x (ours fp32 eager; target 3x)" in peer
    assert "bf16 5.00x (ours bf16 compiled; target 6x, missed)" in peer
    assert any("batch 2 fp32 400 graphs/s (4.00x eager)" in line for line in lines)
