"""The front page: regenerated from the committed run summaries, it matches the committed one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from gns_bench.report.index import baseline_claims, domain_claim, write_index
from gns_bench.sweep.spec import SWEEPS_DIR

REPORTS = SWEEPS_DIR.parent / "reports"


def test_the_committed_front_page_is_what_the_committed_summaries_give(tmp_path: Path) -> None:
    """The test session's MLflow store is empty, so every number comes from the runs.json files in reports/."""
    fresh = write_index(REPORTS, out=tmp_path / "README.md").read_text()
    assert fresh == (REPORTS / "README.md").read_text()


def test_the_front_page_has_a_row_per_claim(tmp_path: Path) -> None:
    text = write_index(REPORTS, out=tmp_path / "README.md").read_text()
    for claim in ("Table 1", "model.message_passing_steps (Fig. 4, Sec. 5.4)", "model.latent_size (App. C.1)",
                  "CONTINUOUS: interpolates friction angles", "FLUIDSHAKE-BOX: the floating box", "CConv",
                  "App. C.6"):
        assert claim in text, claim
    axes = [line for line in text.splitlines() if line.startswith(("| model.", "| train."))
            and "(gns-bench's own target)" not in line]  # not the bench's `train.precision/compile = auto` row
    assert len(axes) == 12


def test_the_domain_row_sets_only_whole_rollouts_beside_the_papers(tmp_path: Path) -> None:
    """A stopped rollout's MSE is over the steps before the stop, the paper's over whole rollouts: the front page
    sets only domains whose rollouts all ran whole beside the paper's numbers and counts the others. Two
    committed cpu summaries, one of them edited to have stopped no rollout."""
    for domain in ("goop", "sand"):
        source = REPORTS / f"domain-{domain}" / "cpu" / "runs.json"
        (tmp_path / f"domain-{domain}" / "cpu").mkdir(parents=True)
        shutil.copy(source, tmp_path / f"domain-{domain}" / "cpu" / "runs.json")
    (row,) = domain_claim(tmp_path)
    assert "2 of 16 domains; no domain's rollouts all ran whole; 2 with rollouts a monitor stopped" in row
    assert "the paper's (median" not in row  # no ratio over a different number of steps than the paper's
    path = tmp_path / "domain-sand" / "cpu" / "runs.json"
    summary = json.loads(path.read_text())
    for run in summary["runs"]:
        run["metrics"]["test/rollout_stopped"] = 0.0
    path.write_text(json.dumps(summary))
    (row,) = domain_claim(tmp_path)
    assert "whole rollouts on 1: rollout MSE" in row and "1 with rollouts a monitor stopped" in row
    (tmp_path / "domain-goop" / "cpu" / "runs.json").unlink()
    (row,) = domain_claim(tmp_path)
    assert "1 of 16 domains" in row and "stopped" not in row


def test_what_is_left_is_extrapolated_per_cpu_generation_where_runs_came_from_several() -> None:
    """Runs that came from two CPU generations sold under one name ("AMD EPYC", families 25 and 26) give the
    overall extrapolation and each generation's own; one generation gives only the overall one."""
    from gns_bench import tracking
    from gns_bench.report.collect import RunRow
    from gns_bench.report.index import _to_go
    from gns_bench.sweep.spec import load_sweep

    planned = load_sweep(SWEEPS_DIR / "domains" / "goop.toml").plan("smoke")[0]

    def row(family: str, minutes: float) -> RunRow:
        metrics = {"train/wall_time_s": 60.0 * minutes, "evaluation_seconds": 0.0}
        tags = {"device": "cpu", "cpu": f"family {family}, model 17, stepping 1, 2596 MHz"}
        return RunRow(planned, tracking.RunRecord("r", planned.name, "FINISHED", 0, {}, metrics, tags))

    runs = [row("26", 30.0), row("26", 30.0), row("25", 60.0), row("25", 60.0)]
    assert _to_go(4, runs) == ("4 models, about 3.0 h (at the mean of CPU family 25, model 17's 2 runs: 4.0 h; "
                               "CPU family 26, model 17's 2 runs: 2.0 h)")
    assert _to_go(4, runs[:2]) == "4 models, about 2.0 h"
    assert _to_go(0, runs) == "none"


def test_a_baseline_row_leads_with_the_like_for_like_comparison(tmp_path: Path) -> None:
    """Sec. 5.5 on GOOP from the committed cpu summaries: the GNS and CConv rollouts ran different numbers of steps
    before a monitor stopped them, so the row leads with the errors against constant velocity over the same steps
    and the steps covered (the verdict's terms), and gives the raw rollout-MSE ratio last, said to be over each
    model's own steps."""
    for sweep in ("domain-goop", "baseline-cconv-goop"):
        (tmp_path / sweep / "cpu").mkdir(parents=True)
        shutil.copy(REPORTS / sweep / "cpu" / "runs.json", tmp_path / sweep / "cpu" / "runs.json")
    claims = baseline_claims(tmp_path)
    (row,) = [line for line in claims if line.startswith("| GOOP: GNS against CConv")]
    ours = row.split(" | ")[2]
    like, steps, raw = ours.split("; ")
    assert like.startswith("against constant velocity, same steps: GNS ") and ", CConv " in like
    assert steps.startswith("rollout steps before a stop: GNS ") and ", CConv " in steps
    assert raw.startswith("raw rollout MSE, each over its own steps: CConv / GNS = ")
    assert "no result yet" in [line for line in claims if "SAND: GNS against CConv" in line][0]


def test_a_generalisation_row_leads_with_the_unseen_scenes_against_constant_velocity(tmp_path: Path) -> None:
    """MULTIMATERIAL's claim is about unseen shapes: its row shows the unseen-shape rollouts beside constant
    velocity on the same steps, and the verdict follows the two numbers (the committed cpu summary, then the
    same one edited so that the GNS does worse than the baseline)."""
    from gns_bench.report.cells import fmt
    from gns_bench.report.index import generalisation_claims

    (tmp_path / "stress-multimaterial" / "cpu").mkdir(parents=True)
    path = tmp_path / "stress-multimaterial" / "cpu" / "runs.json"
    shutil.copy(REPORTS / "stress-multimaterial" / "cpu" / "runs.json", path)
    summary = json.loads(path.read_text())
    metrics = summary["runs"][0]["metrics"]
    mse = metrics["generalisation/multimaterial-blob/rollout_mse"]
    cv = metrics["generalisation/multimaterial-blob/baseline_cv_same_steps_mse"]

    def row() -> str:
        (line,) = [x for x in generalisation_claims(tmp_path) if x.startswith("| MULTIMATERIAL")]
        return line

    ours, verdict = row().split(" | ")[2:5:2]
    assert ours.startswith(f"multimaterial-blob: rollout MSE {fmt(mse)} ({fmt(mse / cv)}x constant velocity, "
                           "same steps; a monitor stopped ")
    assert "; test rollout MSE " in ours
    assert verdict == ("multimaterial-blob: GNS beats constant velocity" if mse < cv
                       else "multimaterial-blob: GNS does not beat constant velocity")
    metrics["generalisation/multimaterial-blob/rollout_mse"] = 2 * cv
    path.write_text(json.dumps(summary))
    assert row().split(" | ")[4] == "multimaterial-blob: GNS does not beat constant velocity"


def test_a_long_rollout_verdict_follows_the_horizon_test_and_the_papers_finding(tmp_path: Path) -> None:
    """BOXBATH's rollouts stay stable in the paper (Sec. 5.3), FLUIDSHAKE-BOX's box slowly loses its shape (App.
    C.7): a monitor stopping ours early fails the first claim and is a faster failure than the second; the same
    committed summaries edited so that nothing stopped read as stable over the whole horizon."""
    from gns_bench.report.index import generalisation_claims

    paths = {}
    for sweep in ("stress-boxbath", "stress-boxbath-shake"):
        (tmp_path / sweep / "cpu").mkdir(parents=True)
        paths[sweep] = tmp_path / sweep / "cpu" / "runs.json"
        shutil.copy(REPORTS / sweep / "cpu" / "runs.json", paths[sweep])

    def rows() -> dict[str, list[str]]:
        return {line.split(":")[0][2:]: line.split(" | ") for line in generalisation_claims(tmp_path)
                if line.startswith(("| BOXBATH", "| FLUIDSHAKE-BOX"))}

    metrics = {s: json.loads(p.read_text())["runs"][0]["metrics"] for s, p in paths.items()}
    box, shake = metrics["stress-boxbath"], metrics["stress-boxbath-shake"]
    assert box["stress/horizon/stopped"] > 0 and shake["stress/horizon/stopped"] > 0  # as committed
    ran = f"{box['stress/horizon/stable_steps']:,.0f} of {box['stress/horizon/steps']:,.0f} steps"
    got = rows()
    tags = {s: json.loads(p.read_text())["runs"][0]["tags"] for s, p in paths.items()}
    assert all("out_of_bounds at step" in t["stress/horizon/trips"] for t in tags.values())  # as committed
    assert f"long rollout: {ran} (" in got["BOXBATH"][2]
    assert "then the out_of_bounds monitor stopped it" in got["BOXBATH"][2]  # the trip names the monitor
    assert got["BOXBATH"][4].startswith("long rollout: not reproduced (the out_of_bounds monitor stopped it at ")
    assert got["FLUIDSHAKE-BOX"][4] == (
        f"long rollout: fails sooner than the paper's (the out_of_bounds monitor stopped it at step "
        f"{shake['stress/horizon/stable_steps']:,.0f} of {shake['stress/horizon/steps']:,.0f})")
    summary = json.loads(paths["stress-boxbath"].read_text())  # the first trip of several names the monitor
    summary["runs"][0]["tags"]["stress/horizon/trips"] = ("long trajectory 0: density_collapse at step 300: x; "
                                                          "long trajectory 1: energy_blowup at step 120: y")
    paths["stress-boxbath"].write_text(json.dumps(summary))
    assert "(the energy_blowup monitor stopped it at " in rows()["BOXBATH"][4]
    del summary["runs"][0]["tags"]["stress/horizon/trips"]  # a summary without the tag: no name to give
    paths["stress-boxbath"].write_text(json.dumps(summary))
    assert rows()["BOXBATH"][4].startswith("long rollout: not reproduced (a monitor stopped it at ")
    for path in paths.values():
        summary = json.loads(path.read_text())
        run = summary["runs"][0]["metrics"]
        run["stress/horizon/stopped"], run["stress/horizon/stable_steps"] = 0.0, run["stress/horizon/steps"]
        path.write_text(json.dumps(summary))
    got = rows()
    whole = f"{box['stress/horizon/steps']:,.0f}"
    assert got["BOXBATH"][4] == f"long rollout: stable over the whole {whole} steps, as the paper's"
    assert "then a monitor stopped it" not in got["BOXBATH"][2]
    assert got["FLUIDSHAKE-BOX"][4].endswith("no failure within the horizon, unlike the paper's")


def test_continuous_interpolates_when_held_out_angles_match_their_trained_neighbours(tmp_path: Path) -> None:
    """App. C.5: the CONTINUOUS row pairs each held-out angle (datasets/continuous.toml) with the trained angles
    adjacent to the held-out interval, each as GNS over constant velocity on the same steps, and asks whether the
    held-out errors exceed their neighbours' by more than the margin (95% interval). A summary (the committed
    smoke one, as if at the cpu tier) with a grid of angles is rewritten for each case."""
    from gns_bench.report.index import generalisation_claims
    from gns_bench.report.stability import held_out_interval

    lo, hi = held_out_interval("continuous")
    (tmp_path / "stress-continuous" / "cpu").mkdir(parents=True)
    shutil.copy(REPORTS / "stress-continuous" / "smoke" / "runs.json", tmp_path / "stress-continuous" / "cpu")
    path = tmp_path / "stress-continuous" / "cpu" / "report.json"  # the stress results the report kept
    kept = json.loads((REPORTS / "stress-continuous" / "smoke" / "report.json").read_text())
    (run_id,) = kept["kept"]["stress"]
    angles = range(0, 85, 5)

    def row(ratio) -> list[str]:
        grid = [{"context": float(a), "rollout_mse": ratio(a) * 1e-3, "baseline_cv_same_steps_mse": 1e-3}
                for a in angles]
        kept["kept"]["stress"][run_id]["generalisation"]["continuous-heldout"]["per_trajectory"] = grid
        path.write_text(json.dumps(kept))
        (line,) = [x for x in generalisation_claims(tmp_path) if x.startswith("| CONTINUOUS")]
        return line.split(" | ")

    held = [a for a in angles if lo <= a <= hi]
    # held-out angles within a few percent of their neighbours (0.2x): interpolates
    cells = row(lambda a: 0.2 * (1.0 + 0.02 * ((a // 5) % 3 - 1)) if lo <= a <= hi else (0.9 if a == 0 else 0.2))
    assert cells[1] == "cpu"
    assert cells[2].startswith(f"rollout MSE over constant velocity's, same steps: held-out angles {lo:g}-{hi:g} deg ")
    assert "held-out against the 2 trained angle(s) adjacent to them: 1x [" in cells[2]
    assert cells[4].startswith("interpolates (held-out no worse than adjacent trained angles by more than 1.25x")
    # 2.5x their neighbours, yet inside the range of all trained angles (0.2x-0.9x): the earlier criterion (no
    # held-out angle worse than the worst trained one) called this interpolation; paired with its neighbours it fails
    cells = row(lambda a: 0.5 if lo <= a <= hi else (0.9 if a == 0 else 0.2))
    assert cells[4].startswith("does not interpolate (") and "lower end is 2.5x" in cells[4]
    # one held-out angle far worse, the others as their neighbours: the interval spans the margin
    cells = row(lambda a: 2.0 if a == held[0] else 0.2)
    assert cells[4].startswith("inconclusive (")


def test_the_scale_verdict_says_which_larger_scenes_ran_their_whole_rollout(tmp_path: Path) -> None:
    """Sec. 5.3's scale claim, per larger scene the stress sweep ran: stable (every step) or where a monitor
    stopped it, beside constant velocity on the same steps (the committed smoke summary, as if at cpu)."""
    from gns_bench.report.cells import fmt
    from gns_bench.report.index import generalisation_claims

    (tmp_path / "stress-waterramps" / "cpu").mkdir(parents=True)
    path = tmp_path / "stress-waterramps" / "cpu" / "runs.json"
    summary = json.loads((REPORTS / "stress-waterramps" / "smoke" / "runs.json").read_text())
    metrics = summary["runs"][0]["metrics"]
    key = "stress/scale/x2/"
    assert metrics[key + "stable_steps"] >= metrics[key + "steps"]  # as committed: it ran every step
    against = fmt(metrics[key + "rollout_mse"] / metrics[key + "baseline_cv_same_steps_mse"])
    scene = f"2x scene ({fmt(metrics[key + 'particle_ratio'])}x the particles)"

    def verdict() -> str:
        path.write_text(json.dumps(summary))
        (line,) = [x for x in generalisation_claims(tmp_path) if x.startswith("| WATERRAMPS")]
        return line.split(" | ")[4]

    assert f"larger scenes: {scene} stable, {against}x constant velocity" in verdict()
    metrics[key + "stable_steps"] = 5.0
    assert (f"larger scenes: {scene} stopped at step 5 of {metrics[key + 'steps']:,.0f}, {against}x constant "
            "velocity") in verdict()


def test_the_radius_ablations_default_point_counts_as_the_goop_model_it_shares() -> None:
    """The runner shares GOOP's run with the radius ablation's R = 0.015 point (the domain's default radius,
    resolved), so the campaign's count of models must see one model there, not two; R = 0.01 stays another."""
    from gns_bench.report.index import _training_key
    from gns_bench.sweep.spec import load_sweep

    radius = {r.name: r for r in load_sweep(SWEEPS_DIR / "ablations" / "connectivity_radius.toml").plan("cpu")}
    (goop,) = load_sweep(SWEEPS_DIR / "domains" / "goop.toml").plan("cpu")
    assert _training_key(radius["connectivity_radius=0.015-seed0"]) == _training_key(goop)
    assert _training_key(radius["connectivity_radius=0.01-seed0"]) != _training_key(goop)
