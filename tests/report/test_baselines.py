"""The baselines report: each baseline's best run beside the GNS run of its domain, the ratio printed with the
two numbers it divides."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from gns_bench.bench import costs as costs_module
from gns_bench.evaluate.result import RolloutResult
from gns_bench.report import baselines, report
from gns_bench.report.collect import RunRow
from gns_bench.report.verdict import error_measure
from gns_bench.sweep.runner import run_sweep
from gns_bench.sweep.spec import SWEEPS_DIR, load_sweep
from gns_bench.tracking import RunRecord

MODEL = "[tiers.smoke.config.model]\nlatent_size = 8\nmlp_hidden_size = 8\nmessage_passing_steps = 1\n"


def test_baselines_report_puts_the_best_baseline_run_beside_the_gns(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")  # its own domain-tiny runs
    root = tmp_path / "sweeps"
    for folder in ("domains", "baselines"):
        (root / folder).mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", root / "tiers.toml")
    (root / "domains" / "tiny.toml").write_text('description = "tiny"\ndomain = "tiny"\n\n' + MODEL)
    (root / "baselines" / "cconv-tiny.toml").write_text(
        'description = "CConv on tiny"\ndomain = "tiny"\nconfig.model = { architecture = "cconv" }\n'
        'default = { "train.noise_std" = 0.0 }\n\n[grid]\n"train.noise_std" = [0.0, 3e-4]\n')
    domain, baseline = load_sweep(root / "domains" / "tiny.toml"), load_sweep(root / "baselines" / "cconv-tiny.toml")
    for sweep in (domain, baseline):
        outcomes = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False)
        assert all(o.status == "FINISHED" for o in outcomes), [o.error for o in outcomes]
    monkeypatch.setattr(baselines, "baseline_sweeps", lambda: [baseline])
    monkeypatch.setattr(baselines, "domain_sweeps", lambda: [domain])
    monkeypatch.setattr(costs_module, "baseline_sweeps", lambda: [baseline])
    monkeypatch.setattr(costs_module, "domain_sweeps", lambda: [domain])
    text = baselines.write_baselines_report("smoke", tmp_path / "reports" / "baselines" / "smoke").read_text()
    (row,) = [line for line in text.splitlines() if line.startswith("| tiny (cconv) |")]
    cells = [c.strip() for c in row.strip("|").split("|")]
    rows = baselines.collect(baseline, "smoke", tmp_path / "reports")
    best, how = baselines.chosen_run(baseline, rows)  # no validation point at the smoke tier: the default setting
    assert best.planned.axes == {"train.noise_std": 0.0} and how.startswith("the default setting")
    assert cells[2] == f"{best.metric('rollout_mse'):.3g} (`{best.planned.name}`: {how})"
    assert cells[3] == "—" and text.splitlines()[2].startswith("**Smoke tier")  # smoke compares nothing
    gns_rows = baselines.collect(domain, "smoke", tmp_path / "reports")
    compared = baselines.comparison_row(baseline, rows, gns_rows, compare_runs=True)
    key, words = error_measure([*gns_rows, best])  # over the same steps for both: never each model's own
    assert key and words and (key == "rollout_mse") == (words == "whole-rollout MSE")
    ratio = best.metric(key) / gns_rows[0].metric(key)
    assert compared[3] == f"{ratio:.3g}x ({best.metric(key):.3g} / {gns_rows[0].metric(key):.3g}, {words})"
    like = (baselines.relative_to_cv(gns_rows[0]), baselines.relative_to_cv(best))
    assert compared[4] == f"{like[0]:.3g}x / {like[1]:.3g}x"
    missing = baselines.comparison_row(baseline, [], gns_rows, compare_runs=True)  # the baseline not run yet
    assert missing[4] == f"{like[0]:.3g}x / —" and missing[2] == "—"
    assert compared[6] == baselines.compare(gns_rows, best).verdict != "—"
    assert "## Verdicts" not in text  # smoke: no verdict drawn
    # cost beside error: the GNS and the baseline's best run, each at its own measured step times
    costs = {c.model: c for c in baselines.costs([(baseline, rows, gns_rows)])}
    assert set(costs) == {"GNS", "CConv"}
    assert costs["CConv"].train_seconds_per_step == pytest.approx(
        best.metric("train/wall_time_s") / best.metric("train/final_step"))
    assert costs["GNS"].rollout_seconds_per_step == pytest.approx(gns_rows[0].metric("rollout_seconds_per_step"))
    assert "## Cost beside error" in text
    assert (tmp_path / "reports" / "baselines" / "smoke" / "cost_vs_error.png").is_file()
    lines = baselines.verdict_lines([(baseline, rows, gns_rows)])
    assert lines[-2].startswith(f"- tiny, GNS against CConv: **{compared[6]}**")
    unpaired = dataclasses.replace(costs["CConv"], against_cv=math.nan)  # no constant velocity over its steps
    monkeypatch.setattr(baselines, "costs", lambda collected: [unpaired])
    section = baselines.cost_section([], tmp_path / "unpaired")
    (cost_row,) = [line for line in section if line.startswith("| tiny | CConv |")]
    assert "| — |" in cost_row and "—x" not in cost_row
    # the baseline sweep's own report: the baselines report's row and verdict, its pictures named for CConv
    monkeypatch.setattr(report, "domain_sweeps", lambda: [domain])
    section = report.baseline_section(baseline, "smoke", rows, tmp_path / "reports", compare=True)
    assert section[0] == "## CConv beside the GNS (Sec. 5.5)"
    assert baselines.HEADER in section and "| " + " | ".join(compared) + " |" in section
    assert baselines.verdict_line(baseline, rows, gns_rows) in section
    page = report.write_sweep_report(baseline, "smoke", tmp_path / "reports" / baseline.name / "smoke").read_text()
    assert "ground truth beside CConv on one frame" in page and "beside the GNS on one frame" not in page
    assert baselines.HEADER in page and baselines.VERDICT_RULE not in page  # smoke: no verdict drawn
    # cost measured side by side: both models timed here on the tier's data, kept in the report's summary
    monkeypatch.setattr(report, "domain_sweeps", lambda: [domain])
    measured = costs_module.measure_costs("smoke", tmp_path / "data", steps=3, echo=lambda line: None)
    timed = {r["model"]: r for r in measured["rows"]}
    assert set(timed) == {"GNS", "CConv"} and measured["missing"] == []
    assert all(r["domain"] == "tiny" and r["train_seconds_per_step"] > 0 and r["rollout_seconds_per_step"] > 0
               for r in timed.values())
    out = tmp_path / "reports" / "baselines" / "smoke"
    text = baselines.write_baselines_report("smoke", out, measured=measured).read_text()
    (cconv_row,) = [line for line in text.splitlines() if line.startswith("| tiny | CConv | ") and "x |" in line]
    over = timed["CConv"]["train_seconds_per_step"] / timed["GNS"]["train_seconds_per_step"]
    assert f"| {over:.3g}x |" in cconv_row and "### Measured side by side" in text
    assert measured["hardware"] in text
    again = baselines.write_baselines_report("smoke", out).read_text()  # not measured again: the table is kept
    assert cconv_row in again.splitlines()
    nothing = costs_module.measure_costs("smoke", tmp_path / "no-data", steps=3, echo=lambda line: None)
    assert nothing["rows"] == [] and len(nothing["missing"]) == 1
    assert "no dataset tiny-smoke-s0" in nothing["missing"][0]
    assert "### Measured side by side" not in "\n".join(baselines.measured_section(nothing))


def test_the_baselines_setting_is_chosen_on_validation_never_on_test() -> None:
    sweep = load_sweep(SWEEPS_DIR / "baselines" / "cconv-goop.toml")
    planned = {p.axes["train.noise_std"]: p for p in sweep.plan("cpu")}

    def row(noise: float, test: float, valid: float | None) -> RunRow:
        metrics = {"test/rollout_mse": test, "test/baseline_cv_same_steps_mse": 1.0}
        if valid is not None:
            metrics |= {"curve/rollout_mse": valid, "curve/baseline_cv_same_steps_mse": 1.0}
        return RunRow(planned[noise], RunRecord(f"id{noise}", planned[noise].name, "FINISHED", 0, metrics=metrics))

    # the noise-free run is better on test, the noisy one on validation: validation chooses
    chosen, how = baselines.chosen_run(sweep, [row(0.0, 0.3, 0.6), row(3e-4, 0.5, 0.4)])
    assert chosen.planned.axes["train.noise_std"] == 3e-4 and how == "chosen on the validation split"
    # no validation point on one of them: nothing fair to choose by, the default stands in, even when worse on test
    chosen, how = baselines.chosen_run(sweep, [row(0.0, 0.5, None), row(3e-4, 0.3, 0.4)])
    assert chosen.planned.axes["train.noise_std"] == 0.0 and how.startswith("the default setting")


@pytest.mark.parametrize(("gns", "baseline", "gns_steps", "baseline_steps", "verdict"), [
    (0.3, 0.6, 200, 200, "yes"),       # lower error against constant velocity, rollouts as long
    (0.3, 0.6, 200, 40, "yes"),        # and the baseline's stopped early (the paper's goop "exploding")
    (0.6, 0.3, 200, 200, "no"),
    (0.3, 0.6, 40, 200, "mixed"),      # lower error, but over rollouts a monitor ended early
    (0.6, 0.3, 200, 40, "mixed"),
    (0.3, float("nan"), 200, 0, "—"),  # the baseline has not run
])
def test_the_verdict_needs_lower_error_and_rollouts_as_long(gns: float, baseline: float, gns_steps: float,
                                                            baseline_steps: float, verdict: str) -> None:
    assert baselines.Comparison(gns, baseline, gns_steps, baseline_steps).verdict == verdict


def _drift(n_steps: int, speed: float, stopped_at: int | None = None) -> RolloutResult:
    """A 2D blob of water drifting right at `speed` a step (ground truth at 0.005)."""
    start = np.random.default_rng(0).uniform(0.3, 0.7, size=(40, 2)).astype(np.float32)
    steps = np.arange(1, n_steps + 1, dtype=np.float32)[:, None, None]
    truth, predicted = (start + s * steps * np.array([1.0, 0.0], np.float32) for s in (0.005, speed))
    window = np.stack([start] * 3)
    return RolloutResult(predicted[:stopped_at], truth, window, np.full(40, 5), stopped_at,
                                   None if stopped_at is None else "out_of_bounds at step 9: a particle left")


def test_the_failure_the_paper_shows_is_drawn_model_beside_model(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    cconv = load_sweep(SWEEPS_DIR / "baselines" / "cconv-goop.toml")
    rollouts = {"gns run": [_drift(30, 0.006)], "cconv run": [_drift(30, 0.02, stopped_at=9)]}
    monkeypatch.setattr(baselines, "best_run", lambda rows: rows[0] if rows else None)
    monkeypatch.setattr(baselines, "chosen_run", lambda sweep, rows: (rows[0] if rows else None, ""))
    monkeypatch.setattr(baselines, "_rollouts", lambda row, workdir: rollouts.get(row, []))
    collected = [(cconv, ["cconv run"], ["gns run"])]
    lines, drawn = baselines.failure_section(collected, tmp_path, previous=None)
    assert drawn == {"goop": {"strip": ["GNS", "CConv"]}}
    assert "## GOOP: the failure the paper shows" in lines and "![GOOP: every model's rollout](goop_strip.png)" in lines
    assert (tmp_path / "goop_strip.png").is_file()
    # MLflow no longer holds the rollouts: the pictures the last report drew stand, and only those
    rollouts.clear()
    assert baselines.failure_section(collected, tmp_path, previous=drawn) == (lines, drawn)
    assert baselines.failure_section(collected, tmp_path, previous=None) == ([], {})
    # a domain where the paper shows no failure gets no strip
    sand = load_sweep(SWEEPS_DIR / "baselines" / "cconv-sand.toml")
    assert baselines.failure_section([(sand, ["cconv run"], ["gns run"])], tmp_path, previous=None) == ([], {})


@dataclasses.dataclass(frozen=True)
class _Row:
    """A run as the failure section sees it once `best_run` picked it (monkeypatched): its id."""
    run_id: str


def _swelling_cube(steps: int) -> RolloutResult:
    """BOXBATH-like: a rigid cube (type 0) that the model swells by 1% a step while the truth holds it."""
    axis = np.arange(4) * 0.02
    cube = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + 0.4
    centre = cube.mean(0)
    truth = np.stack([cube] * steps).astype(np.float32)
    predicted = np.stack([(cube - centre) * (1 + 0.01 * t) + centre for t in range(1, steps + 1)]).astype(np.float32)
    return RolloutResult(predicted, truth, np.stack([cube] * 3), np.zeros(len(cube), int))


def test_a_model_whose_rollouts_are_gone_is_named_not_silently_left_out(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    # The GNS's BOXBATH run is known only from its committed summary (numbers, no artifacts); CConv's is here.
    cconv = load_sweep(SWEEPS_DIR / "baselines" / "cconv-boxbath.toml")
    rollouts = {"cconv run": [_swelling_cube(20)]}
    monkeypatch.setattr(baselines, "best_run", lambda rows: rows[0] if rows else None)
    monkeypatch.setattr(baselines, "chosen_run", lambda sweep, rows: (rows[0] if rows else None, ""))
    monkeypatch.setattr(baselines, "_rollouts", lambda row, workdir: rollouts.get(getattr(row, "run_id", None), []))
    lines, drawn = baselines.failure_section([(cconv, [_Row("cconv run")], [_Row("gns run")])], tmp_path, previous=None)
    curves = drawn["boxbath"].pop("rigidity_curves")
    assert drawn == {"boxbath": {"missing": {"GNS": baselines.MISSING_ROLLOUTS}, "rigidity": ["CConv"],
                                 "strip": ["CConv"]}}
    # the curve the summary keeps: the cube swells 1% a step (drift 0.01 t), the truth holds it (0)
    assert list(curves) == ["CConv"] and curves["CConv"]["run_id"] == "cconv run"
    assert curves["CConv"]["model"][10] == pytest.approx(0.1, rel=1e-3)
    assert max(curves["CConv"]["truth"]) < 1e-6  # 0 up to float32 positions
    assert f"Not drawn: GNS ({baselines.MISSING_ROLLOUTS})." in lines
    assert any(line.endswith("CConv neither. Drawn: CConv.") for line in lines)
    # the baseline's rollout is still drawn against the ground truth: the failure the paper shows is CConv's
    assert (tmp_path / "boxbath_rigidity.png").is_file() and (tmp_path / "boxbath_strip.png").is_file()
    assert "![BOXBATH: every model's rollout](boxbath_strip.png)" in lines
    # a GNS that has not run at all is said to be so
    lines, drawn = baselines.failure_section([(cconv, [_Row("cconv run")], [])], tmp_path, previous=None)
    assert drawn["boxbath"]["missing"] == {"GNS": "not run yet"}


def test_a_stress_sweeps_retraining_of_the_same_model_stands_in_for_gone_gns_rollouts(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cconv = load_sweep(SWEEPS_DIR / "baselines" / "cconv-boxbath.toml")
    (domain_run,) = load_sweep(SWEEPS_DIR / "domains" / "boxbath.toml").plan("cpu")
    (same,) = load_sweep(SWEEPS_DIR / "stress" / "boxbath.toml").plan("cpu")  # its model: the domain run's config
    (other,) = load_sweep(SWEEPS_DIR / "stress" / "boxbath-shake.toml").plan("cpu")  # trained longer
    assert baselines.same_model(domain_run, same) and not baselines.same_model(domain_run, other)

    def row(planned, run_id: str, rollout_mse: float) -> RunRow:
        record = RunRecord(run_id, planned.name, "FINISHED", 0, metrics={"test/rollout_mse": rollout_mse})
        return RunRow(planned, record)

    gns, stand_in, longer = row(domain_run, "gnsgone", 0.0217), row(same, "again", 0.03), row(other, "shake", 0.01)
    rollouts = {"cconv run": [_swelling_cube(20)], "again": [_swelling_cube(20)], "shake": [_swelling_cube(20)]}
    monkeypatch.setattr(baselines, "best_run", lambda rows: rows[0] if rows else None)
    monkeypatch.setattr(baselines, "chosen_run", lambda sweep, rows: (rows[0] if rows else None, ""))
    monkeypatch.setattr(baselines, "_rollouts", lambda row, workdir: rollouts.get(row.run_id, []))
    lines, drawn = baselines.failure_section([(cconv, [_Row("cconv run")], [gns])], tmp_path, previous=None,
                                             stand_ins={"boxbath": [longer, stand_in]})
    assert drawn["boxbath"]["rigidity"] == ["GNS", "CConv"] and "missing" not in drawn["boxbath"]
    assert "stress-boxbath/seed0 (`again`)" in drawn["boxbath"]["gns_from"]
    assert "rollout MSE 0.03 against the domain run's 0.0217" in drawn["boxbath"]["gns_from"]
    assert f"The GNS in these pictures: {drawn['boxbath']['gns_from']}." in lines
    # only a run of the same model stands in: the longer-trained one alone does not
    _, drawn = baselines.failure_section([(cconv, [_Row("cconv run")], [gns])], tmp_path, previous=None,
                                         stand_ins={"boxbath": [longer]})
    assert drawn["boxbath"]["missing"] == {"GNS": baselines.MISSING_ROLLOUTS}


def test_every_model_has_its_own_colour_in_the_comparison_figures() -> None:
    # the rigidity figure once drew the GNS and DPI-Net in one pink (their keys hash to one palette slot)
    colours = [baselines.MODEL_COLOURS[name] for name in ("GNS", "CConv", "DPI-Net")]
    assert len(set(colours)) == 3


def test_a_drift_curve_kept_in_the_summary_is_redrawn_when_its_rollouts_are_gone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # CConv's BOXBATH rollouts went with a lost MLflow store once, and its rigidity curve with them
    cconv = load_sweep(SWEEPS_DIR / "baselines" / "cconv-boxbath.toml")
    rollouts = {"gns run": [_swelling_cube(20)], "cconv run": [_swelling_cube(30)]}
    monkeypatch.setattr(baselines, "best_run", lambda rows: rows[0] if rows else None)
    monkeypatch.setattr(baselines, "chosen_run", lambda sweep, rows: (rows[0] if rows else None, ""))
    monkeypatch.setattr(baselines, "_rollouts", lambda row, workdir: rollouts.get(row.run_id, []))
    _, first = baselines.failure_section([(cconv, [_Row("cconv run")], [_Row("gns run")])], tmp_path, previous=None)
    assert first["boxbath"]["rigidity"] == ["GNS", "CConv"]
    del rollouts["cconv run"]
    lines, drawn = baselines.failure_section([(cconv, [_Row("cconv run")], [_Row("gns run")])], tmp_path,
                                             previous=first)
    assert drawn["boxbath"]["rigidity"] == ["GNS", "CConv"] and drawn["boxbath"]["rigidity_kept"] == ["CConv"]
    assert drawn["boxbath"]["rigidity_curves"]["CConv"] == first["boxbath"]["rigidity_curves"]["CConv"]
    assert drawn["boxbath"]["missing"] == {"CConv": baselines.MISSING_ROLLOUTS}  # the strip still lacks it
    assert any("The curve of CConv is the one the last report drew from the same run" in line for line in lines)
    # another run is CConv's best now: the kept curve is not its own, so CConv is not drawn
    _, drawn = baselines.failure_section([(cconv, [_Row("cconv rerun")], [_Row("gns run")])], tmp_path,
                                         previous=first)
    assert drawn["boxbath"]["rigidity"] == ["GNS"] and "rigidity_kept" not in drawn["boxbath"]
