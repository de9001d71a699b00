"""The kind of machine a run trained on, as the runner and the verdicts read it (gns_bench/sweep/cpu_kinds.py)."""

from __future__ import annotations

from gns_bench.sweep.cpu_kinds import held_kind, kind_of


def test_a_kind_is_the_cpu_generation_or_the_gpu() -> None:
    amd = {"device": "cpu", "hardware": "AMD EPYC, 2 threads", "cpu": "family 25, model 17, stepping 1"}
    assert kind_of(amd) == "family 25, model 17, stepping 1"  # "AMD EPYC" names two generations
    assert kind_of({**amd, "cpu": "family 25, model 17, stepping 1, 2596 MHz"}) == kind_of(
        {**amd, "cpu": "family 25, model 17, stepping 1, 3100 MHz"})  # the clock it ran at is not the kind
    assert kind_of({**amd, "cpu": ""}) == "AMD EPYC, 2 threads"  # no /proc/cpuinfo: the model name
    assert kind_of({**amd, "device": "cuda:0", "hardware": "NVIDIA H200"}) == "NVIDIA H200"
    assert kind_of({}) == ""


def test_the_held_kind_is_where_most_runs_trained_the_first_on_a_tie() -> None:
    assert held_kind(["intel", "amd", "amd", ""]) == "amd"
    assert held_kind(["intel", "amd"]) == "intel"
    assert held_kind(["", ""]) == ""
