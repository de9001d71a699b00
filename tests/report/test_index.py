"""The front page: regenerated from the committed run summaries, it matches the committed one."""

from __future__ import annotations

from pathlib import Path

from gns_bench.report.index import write_index
from gns_bench.sweep.spec import SWEEPS_DIR

REPORTS = SWEEPS_DIR.parent / "reports"


def test_the_committed_front_page_is_what_the_committed_summaries_give(tmp_path: Path) -> None:
    """The test session's MLflow store is empty, so every number comes from the runs.json files in reports/."""
    fresh = write_index(REPORTS, out=tmp_path / "README.md").read_text()
    assert fresh == (REPORTS / "README.md").read_text()


def test_the_front_page_has_a_row_per_claim(tmp_path: Path) -> None:
    text = write_index(REPORTS, out=tmp_path / "README.md").read_text()
    for claim in ("Table 1", "model.message_passing_steps (Fig. 4, Sec. 5.4)", "model.latent_size (App. C.1)",
                  "CONTINUOUS: interpolates friction angles", "CConv", "App. C.6"):
        assert claim in text, claim
    axes = [line for line in text.splitlines() if line.startswith(("| model.", "| train."))
            and "(gns-bench's own target)" not in line]  # not the bench's `train.precision/compile = auto` row
    assert len(axes) == 12
