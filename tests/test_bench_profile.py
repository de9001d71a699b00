"""The profile bench (`python -m gns_bench.bench.profile`): oneDNN's verbose log summarised, and a small real run."""

from __future__ import annotations

import json

import pytest

from gns_bench.bench import profile
from gns_bench.bench.report import _extra_checks

LOG = """onednn_verbose,v1,info,cpu,runtime:OpenMP
onednn_verbose,v1,primitive,exec,cpu,matmul,brg_matmul:avx512_core_bf16,undef,src:bf16,,,mb8,4.0
gns-bench: timed steps start
onednn_verbose,v1,primitive,exec,cpu,matmul,brg_matmul:avx512_core_amx,undef,src:bf16::blocked:ab::f0,,,100x128:128x128,3.0
onednn_verbose,v1,1733500000.1,primitive,exec,cpu,matmul,brg_matmul:avx512_core_amx,undef,src:bf16,,,100x128,5.0
onednn_verbose,v1,primitive,exec,cpu,reorder,jit:uni,undef,src:f32,,,100x128,2.0
onednn_verbose,v1,primitive,create:cache_hit,cpu,matmul,brg_matmul:avx512_core_amx,undef,src:bf16,,,100x128,0.1
some other line, 9.0
"""


def test_the_verbose_log_is_summed_by_kernel_after_the_marker_only() -> None:
    summary = profile.summarise_verbose(LOG.splitlines(), steps=2)
    assert summary["ms_a_step"] == pytest.approx(5.0)  # (3 + 5 + 2) / 2 steps; before the marker and create: not
    matmul, reorder = summary["kernels"]
    assert (matmul["kind"], matmul["implementation"], matmul["calls"]) == ("matmul", "brg_matmul:avx512_core_amx", 1)
    assert matmul["ms_a_step"] == pytest.approx(4.0) and matmul["share"] == pytest.approx(0.8)
    assert (reorder["kind"], reorder["ms_a_step"]) == ("reorder", pytest.approx(1.0))


def test_a_small_profile_names_the_matrix_products(tmp_path) -> None:
    result = profile.operators("bf16", 1, particles=200, neighbours=10.0)
    names = [r["operator"] for r in result["operators"]]
    assert {"aten::mm", "aten::addmm"} & set(names) and result["edges"] > 0
    assert 0 < sum(r["share"] for r in result["operators"]) <= 1.0 + 1e-9
    kernels = profile.kernels("bf16", 1, particles=200, neighbours=10.0, allocator="system")
    assert all(r["ms_a_step"] > 0 for r in kernels["kernels"])  # none at all where torch takes no oneDNN path
    text = profile.markdown([{"operators": result, "kernels": kernels}], "this machine")
    assert "## bf16:" in text and "| `aten::" in text
    (tmp_path / "profile.json").write_text(json.dumps([{"operators": result, "kernels": kernels}]))
    (line,) = _extra_checks(tmp_path)[:-1]  # the machine's line in the bench index
    assert line.startswith("- Training step profile: bf16 `aten::") and "(oneDNN: " in line
