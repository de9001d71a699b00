"""Experiments gns-bench makes or reuses say they are model training, so MLflow 3's UI shows runs, not GenAI."""

from __future__ import annotations

from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from gns_bench import tracking

KIND = {"mlflow.experimentKind": "custom_model_development"}


@pytest.fixture
def client(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> MlflowClient:
    uri = f"sqlite:///{tmp_path / 'm.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    return MlflowClient(tracking_uri=uri)


def test_a_new_experiment_is_tagged_as_model_training(client: MlflowClient) -> None:
    with tracking.start_run("fresh", "r0") as run:
        run.log_metrics({"loss": 1.0}, step=0)
    experiment = client.get_experiment_by_name("fresh")
    assert KIND.items() <= experiment.tags.items()
    assert client.get_run(run.run_id).info.experiment_id == experiment.experiment_id


def test_a_reused_experiment_without_a_kind_gets_it(client: MlflowClient) -> None:
    old = client.create_experiment("older")  # made before gns-bench tagged its experiments, or by other code
    assert "mlflow.experimentKind" not in client.get_experiment(old).tags
    assert tracking.experiment_id("older") == old
    assert KIND.items() <= client.get_experiment(old).tags.items()


def test_a_reused_experiment_keeps_the_kind_it_has(client: MlflowClient) -> None:
    chosen = client.create_experiment("chosen", tags={"mlflow.experimentKind": "genai_development"})
    assert tracking.experiment_id("chosen") == chosen
    assert client.get_experiment(chosen).tags["mlflow.experimentKind"] == "genai_development"


def test_the_cpu_tag_names_the_generation_behind_a_shared_model_name(tmp_path) -> None:
    """"AMD EPYC" names more than one generation; the `cpu` tag keeps the first processor's family, model,
    stepping and clock, and is empty where /proc/cpuinfo is missing."""
    from gns_bench.devices import cpu_identity
    from gns_bench.tracking import environment_tags

    info = tmp_path / "cpuinfo"
    first = ("processor\t: 0\nmodel name\t: AMD EPYC\ncpu family\t: 26\nmodel\t\t: 2\nstepping\t: 1\n"
             "cpu MHz\t\t: 2596.122\n")
    info.write_text(first + "\n" + first.replace("0\n", "1\n", 1).replace("2596.122", "3000.5"))
    assert cpu_identity(info) == "family 26, model 2, stepping 1, 2596 MHz"
    assert cpu_identity(tmp_path / "missing") == ""
    assert environment_tags("cpu")["cpu"] == cpu_identity()


def test_speed_settings_are_cached_per_cpu_generation(tmp_path, monkeypatch) -> None:
    """Two CPUs that share a model name and features but not a generation ("AMD EPYC" of families 25 and 26,
    which differ in speed) get different autotune cache keys."""
    import torch

    from gns_bench import devices

    read = devices._first_processor
    keys = []
    for family in ("25", "26"):
        info = tmp_path / f"cpuinfo-{family}"
        info.write_text(f"processor\t: 0\nmodel name\t: AMD EPYC\ncpu family\t: {family}\nmodel\t\t: 17\n"
                        "flags\t\t: avx512f avx512_bf16\n")
        monkeypatch.setattr(devices, "_first_processor", lambda cpuinfo=None, path=info: read(path))
        assert devices.cpu_generation() == f"family {family}, model 17"
        keys.append(devices.machine_key(torch.device("cpu")))
    assert keys[0] != keys[1]
    assert keys[0].startswith("AMD EPYC (family 25, model 17) [avx512_bf16 avx512f]")


def test_benchmark_folders_keep_two_generations_of_one_model_name_apart(tmp_path) -> None:
    """A bench folder (`devices.machine_slug`) names the CPU's generation: "AMD EPYC" with AVX-512 BF16 of
    families 25 and 26 ran bf16 GEMMs at 417 and 888 GFLOP/s, and one folder for both would overwrite one
    machine's report with the other's."""
    import torch

    from gns_bench.devices import machine_slug

    slugs = []
    for family, model in (("25", "17"), ("26", "2")):
        info = tmp_path / f"cpuinfo-{family}"
        info.write_text(f"processor\t: 0\nmodel name\t: AMD EPYC\ncpu family\t: {family}\nmodel\t\t: {model}\n"
                        "flags\t\t: avx512f avx512_bf16\n")
        slugs.append(machine_slug(torch.device("cpu"), info))
    assert slugs == ["amd-epyc-family-25-model-17-avx512bf16", "amd-epyc-family-26-model-2-avx512bf16"]
    info = tmp_path / "cpuinfo-intel"
    info.write_text("processor\t: 0\nmodel name\t: Intel(R) Xeon(R) Processor\ncpu family\t: 6\nmodel\t\t: 143\n"
                    "flags\t\t: avx512f amx_tile amx_bf16\n")
    assert machine_slug(torch.device("cpu"), info) == "intel-xeon-processor-family-6-model-143-amx"


def test_one_view_answers_a_search_again_from_its_first_answer_and_ends_with_the_block(
        client: MlflowClient, monkeypatch: pytest.MonkeyPatch) -> None:
    with tracking.start_run("sweep:x", "first", tags={"tier": "smoke"}) as run:
        run.log_metrics({"loss": 1.0}, step=0)
    queries = []
    real = tracking._mlflow

    def counted():
        queries.append(1)
        return real()

    monkeypatch.setattr(tracking, "_mlflow", counted)
    with tracking.one_view():
        seen = tracking.search_sweep_runs("sweep:x", "smoke")
        seen[0].tags["tier"] = "changed by a reader"  # a reader's change stays with its copy
        with tracking.one_view():  # nested: the same view
            again = tracking.search_sweep_runs("sweep:x", "smoke")
        with monkeypatch.context() as m:  # logged within the view: not seen by the search it answered before
            m.setattr(tracking, "_mlflow", real)
            with tracking.start_run("sweep:x", "second", tags={"tier": "smoke"}):
                pass
        assert [r.name for r in tracking.search_sweep_runs("sweep:x", "smoke")] == ["first"]
        assert tracking.search_sweep_runs("sweep:x", "other") == []  # another search asks the store
    assert len(queries) == 2 and again[0].tags["tier"] == "smoke" and again[0].run_id == seen[0].run_id
    assert [r.name for r in tracking.search_sweep_runs("sweep:x", "smoke")] == ["second", "first"]  # view ended
