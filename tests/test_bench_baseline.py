"""The speed baseline computes the same function as the optimised model (a speed claim needs this)."""

from __future__ import annotations

import pytest
import torch

from gns_bench.bench.baseline import concatenated_baseline
from gns_bench.bench.measure import build_model, forward_flops, synthetic_scene
from gns_bench.config import ModelConfig


@pytest.mark.parametrize("aggregate", ["messages", "updated_edges"])
def test_baseline_equals_the_split_edge_model(aggregate: str) -> None:
    scene = synthetic_scene(300, dim=2)
    model = build_model(ModelConfig(latent_size=32, mlp_hidden_size=32, message_passing_steps=3, aggregate=aggregate),
                        scene, torch.device("cpu"))
    baseline = concatenated_baseline(model)
    with torch.no_grad():
        a = model(scene.window, scene.particle_type)
        b = baseline(scene.window, scene.particle_type)
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    assert a.abs().mean() > 1e-3


def test_the_gemm_peak_stops_growing_once_a_product_is_slow(monkeypatch: pytest.MonkeyPatch) -> None:
    """A dtype without a hardware path (bf16 on a CPU with no bf16 unit) must not time minute-long products."""
    from gns_bench.bench import measure

    seconds = {256: 0.01, 512: 2.0, 1024: 16.0}  # the second size already slower than GEMM_SECONDS
    timed_sizes: list[int] = []

    def fake_timed(fn, repeats=5, warmup=2, sync=None):
        size = int(fn.__defaults__[0].shape[0])  # the lambda's bound operand
        timed_sizes.append(size)
        return seconds[size]

    monkeypatch.setattr(measure, "timed", fake_timed)
    rate = measure.gemm_peak_gflops(torch.float32, torch.device("cpu"), sizes=(1024, 256, 512))
    assert timed_sizes == [256, 512]  # smallest first, and none after the slow one
    assert rate == pytest.approx(max(2 * n**3 / seconds[n] / 1e9 for n in (256, 512)))


def test_forward_flops_count_every_linear_layer() -> None:
    scene = synthetic_scene(100, dim=2)
    config = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1, mlp_hidden_layers=0)
    model = build_model(config, scene, torch.device("cpu"))
    n, e = 100, 1000
    node_in = model.network.node_encoder[0].in_features
    expected = 2 * (node_in * 8 * n + 3 * 8 * e + 8 * 2 * n)  # node encoder, edge encoder (3 inputs), decoder
    expected += 2 * (8 * 8 * e + 16 * 8 * n + 16 * 8 * n)  # split edge layer: edge part, node projections; node MLP
    assert forward_flops(model, n, e) == expected


def test_bench_writes_json_markdown_and_plot(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    from PIL import Image

    from gns_bench import autotune
    from gns_bench.bench.report import write_bench_index
    from gns_bench.bench.run import BenchSettings, run_bench
    from gns_bench.devices import usable_cores

    # a machine with a bf16 unit, so auto's probe times both precisions (without one it times only fp32)
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: autotune.MatmulRates(fp32=184.0, bf16=913.0))
    results = run_bench(tmp_path / "this-machine", BenchSettings.tiny(), log_to_mlflow=False)
    index = write_bench_index(tmp_path).read_text()  # every machine's targets, linking to its tables
    env = results["environment"]  # the CPU's generation beside its model name (one name covers two AMD EPYCs)
    machine = env["hardware"] if env["device"].startswith("cuda") else f"{env['hardware']} (CPU {env['cpu']})"
    assert f"## {machine} (quick sizes)" in index
    assert "[this-machine/](this-machine/README.md)" in index and "waterdrop rollout step <= 25 ms" in index
    tmp_path = tmp_path / "this-machine"
    saved = json.loads((tmp_path / "bench.json").read_text())
    assert saved["train"][0]["steps_per_s"] > 0 and len(saved["train"]) == 4
    assert {r["precision"] for r in results["inference"]} == {"fp32", "bf16"}
    assert saved["scaling"][0]["peak_memory_mb"] > 0
    readme = (tmp_path / "README.md").read_text()
    assert "## Targets" in readme and "PyG MessagePassing baseline" in readme and "waterdrop" in readme
    pick = saved["autotune"]  # what train.precision = "auto" picks, judged against the variants timed at length
    assert pick["precision"] in ("fp32", "bf16") and set(pick["probe_step_s"]) == {"fp32", "bf16"}
    assert "auto within 5% of the fastest variant" in readme and f"auto picked {pick['precision']}" in readme
    threads = pick["threads"]  # and what train.num_threads = "auto" picks, the bench's own count restored after
    assert set(threads["step_s"]) == {str(n) for n in autotune.thread_counts(usable_cores())}
    assert f"num_threads = auto picked {threads['chosen']} (fp32 eager" in readme
    assert torch.get_num_threads() == env["threads"]
    assert "waterdrop rollout step <= 25 ms (bf16" in readme and "its matmuls alone need" in readme
    rates = saved["steadiness"]  # the square-GEMM rate again at the end, beside the start's the rows were judged by
    assert set(rates) == {"fp32", "bf16"} and all(r["end"] > 0 for r in rates.values())
    assert all(rates[row["precision"]]["start"] == row["gemm_peak_gflops"] for row in saved["train"])
    assert "the square-GEMM rate at its start and end, fp32" in readme
    with Image.open(tmp_path / "bench_scaling.png") as image:
        assert image.size[0] > 300
    skips = saved["skips"]  # the kinematic skip: every synthetic share, both precisions, the same predictions
    assert {(r["kinematic_share"] > 0.1, r["precision"]) for r in skips} == {
        (k, p) for k in (False, True) for p in ("fp32", "bf16")}
    assert all(r["full_s"] > 0 and r["moving_only_s"] > 0 for r in skips)
    assert all(r["max_difference"] <= (1e-4 if r["precision"] == "fp32" else 5e-2) for r in skips)
    assert "## Skipping kinematic particles' work in a rollout step" in readme
    # the one-step forward at the settings' sizes (the full bench's 2,000-particle graphs of 16 windows took a
    # minute of this test's two)
    assert [(r["particles"], r["windows"]) for r in saved["one_step"]] == [(100, 1), (100, 2)]


def test_a_run_whose_machine_slowed_down_says_so_and_a_steady_one_says_it_held() -> None:
    from gns_bench.bench.report import steadiness

    steady = {"steadiness": {"fp32": {"start": 263.0, "end": 250.0}, "bf16": {"start": 1000.0, "end": 1100.0}}}
    assert steadiness(steady).startswith("The machine held its speed through the run")
    assert "fp32 263 then 250 GFLOP/s, bf16 1000 then 1100 GFLOP/s" in steadiness(steady)
    slowed = {"steadiness": {"fp32": {"start": 263.0, "end": 250.0}, "bf16": {"start": 2368.0, "end": 679.0}}}
    assert steadiness(slowed).startswith("**The machine's speed changed during this run**")
    assert "71% apart" in steadiness(slowed)  # the larger change of the two: 679 / 2368 - 1
    assert steadiness({"train": []}) == ""  # a run from before the check says nothing rather than guess


def test_compiled_rollout_steps_are_timed_after_the_eager_ones_and_judged_against_the_target() -> None:
    import torch

    from gns_bench.bench.report import rollout_target
    from gns_bench.bench.run import BenchSettings, measure_inference

    settings = BenchSettings(inference_domains=[("waterdrop", 2, 300), ("boxbath", 3, 200)], repeats=1,
                             compile=True, compiled_rollout_domains=("waterdrop",))
    rows = measure_inference(settings, torch.device("cpu"))
    assert [(r["domain"], r["precision"], r["compiled"]) for r in rows] == [
        ("waterdrop", "fp32", False), ("waterdrop", "bf16", False), ("boxbath", "fp32", False),
        ("boxbath", "bf16", False), ("waterdrop", "fp32", True), ("waterdrop", "bf16", True)]
    assert all(0 < r["matmul_floor_s"] and r["forward_gflop"] > 0 for r in rows)
    fastest = min((r for r in rows if r["domain"] == "waterdrop" and r["precision"] == "bf16"),
                  key=lambda r: r["step_s"])
    target = rollout_target({"inference": rows})
    assert target["met"] == (fastest["step_s"] <= 0.025)
    assert target["measured"].startswith(f"{fastest['step_s'] * 1e3:.1f} ms (")


def test_a_gpus_report_says_what_its_small_graphs_cost_from_its_own_scaling_rows() -> None:
    """The committed H200 benchmark: the reasons paragraph adds the per-particle cost of the smallest and largest
    2D scenes; a CPU's does not."""
    import json
    from pathlib import Path

    from gns_bench.bench.report import why_missed

    bench = Path(__file__).parents[1] / "reports/bench"
    gpu = json.loads((bench / "cuda-nvidia-h200/bench.json").read_text())
    rows = sorted((r for r in gpu["scaling"] if r["dim"] == 2), key=lambda r: r["particles"])
    first = f"{rows[0]['step_s'] / rows[0]['particles'] * 1e6:.2g} µs a particle at {rows[0]['particles']:,}"
    last = f"against {rows[-1]['step_s'] / rows[-1]['particles'] * 1e6:.2g} at {rows[-1]['particles']:,}"
    assert first in why_missed(gpu) and last in why_missed(gpu)
    cpu = json.loads((bench / "amd-epyc-family-25-model-17-avx512bf16/bench.json").read_text())
    assert "µs a particle" not in why_missed(cpu)


def test_a_machine_with_no_bf16_unit_benches_fp32_alone_and_its_report_says_why(monkeypatch, tmp_path) -> None:
    """Where bf16 products run in a fallback, the bench times fp32 alone (`bench_precisions`), and the report
    says which targets were not measured and why, rather than judging them or failing on the missing rows."""
    import json
    from pathlib import Path

    from gns_bench import autotune
    from gns_bench.bench.report import targets, write_bench_index, write_bench_report
    from gns_bench.bench.run import BenchSettings, bench_precisions, measure_training
    from gns_bench.report.index import bench_claims

    cpu = torch.device("cpu")
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: autotune.MatmulRates(fp32=92.0, bf16=2.0))
    precisions, left_out = bench_precisions(BenchSettings(), cpu)
    assert precisions == ("fp32",) and "ran 2 GFLOP/s in bf16 against 92 in fp32" in left_out
    assert bench_precisions(BenchSettings(precisions=("fp32", "bf16")), cpu) == (("fp32", "bf16"), "")  # as asked
    monkeypatch.setattr(autotune, "matmul_rates", lambda device, **kw: autotune.MatmulRates(fp32=184.0, bf16=913.0))
    assert bench_precisions(BenchSettings(), cpu) == (("fp32", "bf16"), "")
    rows = measure_training(BenchSettings.tiny(), cpu, ("fp32",))
    assert {r["precision"] for r in rows} == {"fp32"} and len(rows) == 2  # ours and the PyG port

    # a committed two-precision run with its bf16 rows taken out stands for such a machine's results
    committed = Path(__file__).parents[1] / "reports/bench/amd-epyc-family-26-model-2-avx512bf16/bench.json"
    results = json.loads(committed.read_text())
    for section in ("train", "inference", "skips", "static_encodings"):
        results[section] = [r for r in results[section] if r["precision"] == "fp32"]
    results["left_out"] = left_out
    judged = {t["target"]: t for t in targets(results)}
    bf16 = [t for name, t in judged.items() if "bf16" in name]
    assert len(bf16) == 3 and all(t["met"] is None and left_out in t["measured"] for t in bf16)
    assert all(isinstance(t["met"], bool) for name, t in judged.items() if "bf16" not in name)
    folder = tmp_path / "bench" / "no-bf16-unit"
    folder.mkdir(parents=True)
    (folder / "bench.json").write_text(json.dumps(results))
    readme = write_bench_report(results, folder)[0].read_text()
    assert "| not measured |" in readme and "which this machine cannot speed up (bf16 left out" in readme
    assert "our fastest bf16 step" not in readme
    write_bench_index(tmp_path / "bench")
    claims = "\n".join(bench_claims(tmp_path))
    assert "(bf16) (gns-bench's own target) | bench |" in claims and "| not measured |" in claims
    (tmp_path / "bench" / "with-bf16").mkdir()  # beside a machine that measured every target
    (tmp_path / "bench" / "with-bf16" / "bench.json").write_text(committed.read_text())
    claims = "\n".join(bench_claims(tmp_path))
    assert "| met (1 did not measure it) |" in claims  # the bf16 GEMM-rate target, met on family 26
