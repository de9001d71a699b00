"""The evaluation bench (`python -m gns_bench.bench.evaluation`): its rows hold what they claim on a small dataset."""

from __future__ import annotations

import json
import math
from pathlib import Path

from gns_bench.bench import evaluation
from gns_bench.bench.report import _extra_checks


def test_the_evaluation_bench_compares_like_with_like(tiny_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "machine"
    evaluation.main(["--out", str(out), "--dataset", str(tiny_dataset), "--repeats", "1"])
    results = json.loads((out / "evaluation.json").read_text())
    rows = {r["selection"]: r for r in results["selections"]}
    assert set(rows) == {"all four", "rollout", "one-step"}
    assert rows["rollout"]["rollout_mse"] == rows["all four"]["rollout_mse"]  # the same rollout either way
    assert math.isnan(rows["one-step"]["rollout_mse"]) and math.isnan(rows["rollout"]["one_step_mse"])
    assert rows["one-step"]["one_step_mse"] == rows["all four"]["one_step_mse"]
    (skin,) = results["skins"]
    assert skin["same_edges"] and skin["checked_skin_radii"] > 0 and skin["frames"] > 1 and 0 < skin["search_share"]
    assert skin["probe"].startswith("skin ") and "probed on true frames" in skin["probe"]
    index = "\n".join(_extra_checks(out))  # the machine's lines in the bench index
    assert "one-step 0." in index and "same edges" in index, index
