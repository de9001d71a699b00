"""Reports from MLflow: a tiny domain sweep and a 2-value ablation sweep run for real, then reported.

Checks structure, not accuracy: every planned run has a row (missing ones marked), run ids are MLflow's,
the paper's numbers stand beside ours, and every figure is a readable, small PNG or GIF.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from PIL import Image

from gns_bench import tracking
from gns_bench.cli import main
from gns_bench.report import write_all_reports, write_report
from gns_bench.report.cells import budget_statement, cv_ratio, mean_cell
from gns_bench.report.collect import collect, domain_sweeps, load_rollouts
from gns_bench.report.figures import pareto_front
from gns_bench.report.reference import ablation_reference, display_name, domain_reference, inference_reference
from gns_bench.report.report import accuracy_row, write_domains_report
from gns_bench.sweep.runner import run_sweep
from gns_bench.sweep.spec import SWEEPS_DIR, load_sweep

EVAL = '\n[tiers.smoke.config.eval]\nmax_trajectories = 2\n'
DOMAIN = 'description = "tiny domain"\ndomain = "tiny"\npaper_figure = "Table 1"\n'
ABLATION = ('description = "noise std on tiny"\ndomain = "tiny"\npaper_figure = "Fig. 4"\n\n[grid]\n'
            '"train.noise_std" = [0.0, 3e-4, 1e-3]\n')
ABLATION_TIER = '\n[tiers.smoke]\nseeds = [0, 1]\ngrid = { "train.noise_std" = [0.0, 3e-4] }\n'
MAX_FIGURE_BYTES = 400_000
ACCURACY_CELLS = 13  # columns of the accuracy table (shaped like the paper's Table 1)
BUDGET_CELLS = 8  # columns of the budget table (the diagnostics table has as many: read it after its heading)


@pytest.fixture(scope="module")
def swept(tmp_path_factory: pytest.TempPathFactory, smoke_model: str) -> dict[str, Path]:
    """Run both sweeps once (6 tiny runs, a few seconds each) into the session's MLflow store."""
    root = tmp_path_factory.mktemp("report")
    sweeps = root / "sweeps"
    for folder, name, text in (("domains", "tiny", DOMAIN + smoke_model + EVAL),
                               ("ablations", "noise_std", ABLATION + smoke_model + EVAL + ABLATION_TIER)):
        (sweeps / folder).mkdir(parents=True, exist_ok=True)
        (sweeps / folder / f"{name}.toml").write_text(text)
    shutil.copy(SWEEPS_DIR / "tiers.toml", sweeps / "tiers.toml")
    paths = {"domain": sweeps / "domains" / "tiny.toml", "ablation": sweeps / "ablations" / "noise_std.toml"}
    statuses = {}
    for kind, path in paths.items():
        outcomes = run_sweep(load_sweep(path), "smoke", data_root=root / "data", runs_root=root / "runs",
                             progress=False, echo=lambda _: None)
        assert all(o.status in ("FINISHED", "SHARED") for o in outcomes), [o.error for o in outcomes]
        statuses.update({f"{kind}/{o.name}": o.status for o in outcomes})
    # The ablation's default point (noise 3e-4, seed 0) is the domain sweep's run: recorded, not retrained.
    assert [name for name, status in statuses.items() if status == "SHARED"] == ["ablation/noise_std=0.0003-seed0"]
    return {**paths, "root": root}


def check_figures(readme: Path, expected: set[str]) -> None:
    """Every expected figure is linked from the README, non-empty, readable and small."""
    text = readme.read_text()
    linked = set(re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text))
    assert expected <= linked, expected - linked
    for name in linked:
        path = readme.parent / name
        assert 0 < path.stat().st_size < MAX_FIGURE_BYTES, (name, path.stat().st_size)
        if name.endswith(".png"):
            image = matplotlib.image.imread(path)
            assert image.ndim == 3 and min(image.shape[:2]) > 50 and image.std() > 0
        else:
            with Image.open(path) as gif:
                assert gif.format == "GIF" and gif.n_frames > 1


def table_rows(text: str, first_cell: str, min_cells: int = 0, exact: bool = False) -> list[list[str]]:
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith(f"| {first_cell} ")]
    return [r for r in rows if (len(r) == min_cells if exact else len(r) >= min_cells)]


def budget_part(text: str) -> str:
    """A report's budget table and what follows it."""
    return text.split("\n## Budget\n", 1)[1]


def test_domain_sweep_report(swept: dict[str, Path], tmp_path: Path) -> None:
    sweep = load_sweep(swept["domain"])
    readme = write_report(swept["domain"], "smoke", tmp_path)
    assert readme == tmp_path / "domain-tiny" / "smoke" / "README.md"
    text = readme.read_text()
    assert text.splitlines()[2].startswith("**Smoke tier: a pipeline check, not a result.**")  # said first
    (run,) = [r for r in tracking.search_sweep_runs(sweep.experiment, "smoke")]
    (accuracy,) = table_rows(text, "tiny", ACCURACY_CELLS, exact=True)
    assert float(accuracy[8]) == pytest.approx(run.metrics["test/rollout_mse"], rel=1e-2)
    assert float(accuracy[7]) == pytest.approx(run.metrics["test/mse_h10"], rel=1e-2)  # steps 1-10, every domain
    assert accuracy[6] == accuracy[10] == accuracy[11] == "—" and accuracy[12] == "1"  # smoke: no comparison
    (distribution,) = table_rows(text, "tiny", 5, exact=True)
    assert float(distribution[1]) == pytest.approx(run.metrics["test/ot"], rel=1e-2)  # OT column from MLflow
    (budget,) = table_rows(budget_part(text), "tiny", BUDGET_CELLS, exact=True)
    assert budget == ["tiny", "20", "fp32", budget[3], budget[4], "smoke", "ok", f"`{run.run_id}`"]
    for term in ("one-step MSE", "rollout MSE", "GNS / constant velocity", "OT", "MMD", "KE error"):
        assert f"- **{term}**:" in text  # every metric shown is defined where the report starts
    # Compared (any tier but smoke): the ratio beside the two numbers it divides, the baseline over the same steps
    rows = collect(sweep, "smoke")
    cv = run.metrics["test/baseline_cv_same_steps_mse"]
    rollout = run.metrics["test/rollout_mse"]
    assert accuracy_row(sweep, rows, compare=True)[11] == f"{rollout / cv:.3g}x ({rollout:.3g} / {cv:.3g})"
    statement = budget_statement(rows, "small")
    assert "**Far below the paper's budget**" in statement and "20,000,000" in statement
    assert "The ground truth comes from gns-bench's own solvers" in statement  # the tiny dataset is made here
    assert "`eval.rollout_steps` = 10 steps" in statement
    check_figures(readme, {"time_vs_error.png", "rollout_best.png", "rollout_best.gif", "rollout_worst.png",
                           "rollout_worst.gif"})


def test_a_report_written_again_draws_its_rollouts_only_when_they_are_not_there(
        swept: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from gns_bench.report import figures

    drawn: list[str] = []

    def counting(real):
        def counted(result, path, *args, **kwargs):
            drawn.append(path.name)
            return real(result, path, *args, **kwargs)
        return counted

    for name in ("rollout_png", "rollout_gif"):
        monkeypatch.setattr(figures, name, counting(getattr(figures, name)))
    first = write_report(swept["domain"], "smoke", tmp_path).read_text()
    pictures = sorted(drawn)
    assert "rollout_best.gif" in pictures and "rollout_best.png" in pictures
    drawn.clear()
    assert write_report(swept["domain"], "smoke", tmp_path).read_text() == first  # the same run, the same page
    assert drawn == []  # and its pictures, there already, are not drawn again
    (tmp_path / "domain-tiny" / "smoke" / "rollout_best.gif").unlink()
    assert write_report(swept["domain"], "smoke", tmp_path).read_text() == first
    assert sorted(drawn) == pictures  # one picture gone: the run's pictures are drawn again


def test_ablation_sweep_report_marks_missing_values(swept: dict[str, Path], tmp_path: Path) -> None:
    path = swept["ablation"]
    path.write_text(path.read_text().replace('[0.0, 3e-4] }', '[0.0, 3e-4, 1e-3] }'))  # 1e-3 never ran
    readme = write_report(path, "smoke", tmp_path)
    text = readme.read_text()
    assert "Paper default: 0.0003" in text
    rows = {r[0]: r for r in table_rows(text, "0") + table_rows(text, "0.0003") + table_rows(text, "0.001")}
    assert rows["0"][1] == "2/2" and rows["0.0003"][1] == "2/2" and rows["0.001"][1] == "0/2"
    assert all(cell == "**missing**" for cell in rows["0.001"][2:7]) and rows["0.001"][7] == "—"
    assert all("±" in cell for cell in rows["0"][2:6])
    # Whole 10-step rollouts (nothing stopped), and the GNS against constant velocity over them.
    row_runs = [r for r in collect(load_sweep(path), "smoke") if r.planned.axes["train.noise_std"] == 0.0]
    assert len(row_runs) == 2
    assert rows["0"][6] == "10" and rows["0"][7] == "—"  # smoke: no comparison printed
    gns = np.mean([r.metric("rollout_mse") for r in row_runs])
    cv = np.mean([r.metric("baseline_cv_same_steps_mse") for r in row_runs])
    assert cv_ratio(row_runs) == f"{gns / cv:.3g}x ({gns:.3g} / {cv:.3g})"
    assert "Verdict" not in text  # nor a verdict on the paper's finding
    assert "cover different steps" not in text
    runs = tracking.search_sweep_runs("sweep:ablation-noise_std", "smoke")
    assert len(runs) == 4 and all(f"`{r.run_id}`" in text for r in runs)
    missing_runs = [line for line in text.splitlines() if line.startswith("| noise_std=0.001-seed")]
    assert len(missing_runs) == 2 and all("**missing**" in line for line in missing_runs)
    assert "OT method: exact EMD" in text
    check_figures(readme, {"ablation_noise_std.png", "time_vs_error.png", "rollout_best.gif"})

    # The shared default point cites the domain run it copies, whose artifacts stand in for its own.
    (domain_run,) = tracking.search_sweep_runs("sweep:domain-tiny", "smoke")
    (shared,) = [r for r in collect(load_sweep(path), "smoke") if r.planned.name == "noise_std=0.0003-seed0"]
    (line,) = [line for line in text.splitlines() if line.startswith("| noise_std=0.0003-seed0 ")]
    assert f"shared from domain-tiny/seed0 (`{domain_run.run_id}`)" in line
    assert shared.artifact_run_id == domain_run.run_id != shared.run_id
    npz = f"evaluation/{shared.split}_rollouts.npz"
    assert load_rollouts(shared.artifact_run_id, npz, tmp_path / "a") and not load_rollouts(shared.run_id, npz,
                                                                                              tmp_path / "b")


def test_domains_aggregate_keeps_missing_domains(swept: dict[str, Path], tmp_path: Path) -> None:
    goop = next(s for s in domain_sweeps() if s.name == "domain-goop")
    readme = write_domains_report([load_sweep(swept["domain"]), goop], "smoke", tmp_path)
    text = readme.read_text()
    (tiny,) = table_rows(budget_part(text), "tiny", BUDGET_CELLS, exact=True)
    (goop_budget,) = table_rows(budget_part(text), "GOOP", BUDGET_CELLS, exact=True)
    assert tiny[-2] == "ok" and goop_budget[-2] == "**missing**" and goop_budget[-1] == "—"
    (goop_row,) = table_rows(text, "GOOP", ACCURACY_CELLS, exact=True)
    assert goop_row[4] == "**missing**" and goop_row[5] == "2.91e-09" and goop_row[9] == "0.00189"
    assert goop_row[11] == "—" and goop_row[12] == "0"  # no run, so no baseline and no seed
    assert "1 of 2 with a finished run" in text
    assert "time_vs_error.png" not in text  # no time-against-error front across domains

    every = write_report("domains", "smoke", tmp_path / "all").read_text()
    names = [domain_reference(s.domain).name for s in domain_sweeps()]
    assert len(names) == 16
    for name in names:
        (row,) = table_rows(budget_part(every), name, BUDGET_CELLS, exact=True)
        assert row[-2] == "**missing**"


def test_cli_report_and_unknown_sweep(swept: dict[str, Path], tmp_path: Path) -> None:
    assert main(["report", str(swept["domain"]), "--tier", "smoke", "--reports-root", str(tmp_path)]) == 0
    assert (tmp_path / "domain-tiny" / "smoke" / "README.md").is_file()
    with pytest.raises(ValueError, match="no sweep named"):
        write_report("ablation-no_such_axis", "smoke", tmp_path)
    assert tracking.search_sweep_runs("sweep:never-ran") == []
    assert collect(load_sweep(swept["domain"]), "small")[0].status == "missing"


def test_all_reports_cover_the_sweeps_with_runs(swept: dict[str, Path], tmp_path: Path) -> None:
    written = write_all_reports("smoke", tmp_path, sweeps_dir=swept["root"] / "sweeps")
    assert [p.relative_to(tmp_path).parts[0] for p in written] == [
        "domain-tiny", "ablation-noise_std", "domains", "stability", "baselines", "README.md"]  # front page last
    assert all(p.name == "README.md" and p.stat().st_size > 0 for p in written)
    # At a tier with no runs only the two overviews are written, their rows all marked missing.
    small = tmp_path / "small"
    assert main(["report", "all", "--tier", "small", "--reports-root", str(small)]) == 0
    assert sorted(p.name for p in small.iterdir()) == ["README.md", "baselines", "domains", "stability"]


def test_pareto_front_and_references() -> None:
    cost = np.array([1.0, 2.0, 3.0, 1.5, np.nan])
    error = np.array([5.0, 1.0, 0.5, 6.0, 0.1])
    assert pareto_front(cost, error).tolist() == [0, 1, 2]
    noise = ablation_reference("train.noise_std")
    assert (noise["default"], noise["scale"]) == (3e-4, "log") and [3e-4, 0.0] in noise["better"]  # Fig. 4
    assert ablation_reference("model.latent_size")["no_effect"] is True  # App. C.1
    assert ablation_reference("model.message_passing_steps")["scale"] == "linear"
    assert domain_reference("tiny") is None
    assert display_name("tiny") == "tiny" and display_name("water-3d-s") == "WATER-3D-S"
    water = domain_reference("waterdrop")
    assert water.rollout_mse == pytest.approx(7.01e-3) and water.cconv_rollout_mse == pytest.approx(18e-3)
    assert inference_reference(2, "MPM (2D)")["gns_seconds"] == [0.025, 0.059]
    assert inference_reference(3, "SPH (3D)")["gns_seconds"] == [0.25, 0.36]
    assert inference_reference(3, "PBD (3D)") is None


@pytest.mark.parametrize("axis, values, x, xscale, default_at", [
    ("model.position_encoding", ["relative", "absolute"], [0, 1], "linear", 0),  # categories: 0, 1, ...
    ("model.shared_processor", [False, True], [0, 1], "linear", 0),
    ("train.noise_std", [0.0, 1e-4, 3e-4, 1e-2], [0.0, 1e-4, 3e-4, 1e-2], "symlog", 3e-4),  # log, with 0
])
def test_ablation_figure_for_categorical_and_log_axes(axis: str, values: list, x: list[float], xscale: str,
                                                      default_at: float, tmp_path: Path) -> None:
    import matplotlib.pyplot as plt

    from gns_bench.report.figures import PANELS, ablation_figure, draw_ablation

    # a different mean and std for each panel and value, spanning decades: a panel showing another metric's
    # or value's numbers fails
    stats = {m: [(10.0 ** -(2 * i + 3) * (j + 1), 1e-10 * (i + 1) * (j + 1), 2) for i in range(len(values))]
             for j, (m, _) in enumerate(PANELS)}
    fig = draw_ablation(axis, values, stats, ablation_reference(axis))
    assert [ax.get_title() for ax in fig.axes] == [label for _, label in PANELS]
    for ax, (metric, _) in zip(fig.axes, PANELS, strict=True):
        assert ax.get_xlabel() == axis.split(".")[-1]
        (errorbar,) = ax.containers
        points, _, (bars,) = errorbar.lines
        np.testing.assert_allclose(points.get_xdata(), x)
        np.testing.assert_allclose(points.get_ydata(), [s[0] for s in stats[metric]])
        np.testing.assert_allclose([(b[1, 1] - b[0, 1]) / 2 for b in bars.get_segments()],
                                   [s[1] for s in stats[metric]], rtol=1e-6)  # error bars: the std
        (default,) = [line for line in ax.get_lines() if line.get_label() == "paper default"]
        assert default.get_xdata()[0] == pytest.approx(default_at)
        assert ax.get_xscale() == xscale and ax.get_yscale() == "log"
        if xscale == "linear":  # categories are named on the axis
            assert [t.get_text() for t in ax.get_xticklabels()] == [str(v) for v in values]
    plt.close(fig)
    path = ablation_figure(axis, values, stats, ablation_reference(axis), tmp_path / "a.png")
    image = matplotlib.image.imread(path)
    assert image.shape[1] > image.shape[0] > 100 and image.std() > 0


def test_budget_statement_flags_rollouts_stopped_by_monitors() -> None:
    from gns_bench.report.cells import budget_statement
    from gns_bench.report.collect import RunRow

    planned = load_sweep(SWEEPS_DIR / "domains" / "goop.toml").plan("smoke")[0]

    def row(run_id: str, stopped: float) -> RunRow:
        record = tracking.RunRecord(run_id, planned.name, "FINISHED", 0, {"train.steps": "20"},
                                    {"test/rollout_stopped": stopped, "test/rollout_mse": 1e-3})
        return RunRow(planned, record)

    text = budget_statement([row("aaa", 0.5), row("bbb", 0.0)])
    assert "In 1 of 2 runs a health monitor stopped some rollouts early" in text and "`aaa`" in text
    assert "health monitor" not in budget_statement([row("bbb", 0.0)])
    # every run stopped: said so, without a list of IDs that the report's tables already give
    every = budget_statement([row("aaa", 0.5), row("ccc", 1.0)])
    assert "In every run (2 of 2) a health monitor stopped" in every and "`aaa`" not in every
    assert every.startswith("**Budget.**") and "\n- **Stopped rollouts.**" in every  # a caveat a bullet


def test_a_run_that_shared_its_cores_is_marked_wherever_its_training_time_shows() -> None:
    """`train/oversubscribed` (LoadWatch: another job competed while the run trained): the budget statement
    names the run and how, and the Budget table's training time carries the mark; a clean run has neither."""
    from gns_bench.report.cells import SHARED_CORES, budget_statement
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import budget_row

    sweep = load_sweep(SWEEPS_DIR / "domains" / "goop.toml")
    planned = sweep.plan("smoke")[0]
    how = "load above 2.5 (2 cores) at 7 of 74 logged steps, up to 3.5"

    def row(run_id: str, tags: dict[str, str]) -> RunRow:
        metrics = {"test/rollout_mse": 1e-3, "train/wall_time_s": 600.0, "train/final_step": 20.0}
        return RunRow(planned, tracking.RunRecord(run_id, planned.name, "FINISHED", 0, {"train.steps": "20"},
                                                  metrics, tags))

    shared, clean = row("aaa", {"train/oversubscribed": how}), row("bbb", {})
    text = budget_statement([shared, clean])
    assert "In 1 of 2 runs another job competed for the cores" in text and f"`aaa`: {how}" in text
    assert "`bbb`" not in text.split("competed")[1].split(". ")[0]
    assert budget_row(sweep, [shared, clean])[3] == f"10 {SHARED_CORES}"
    assert "competed" not in budget_statement([clean]) and budget_row(sweep, [clean])[3] == "10"


def test_runs_on_two_generations_of_one_cpu_model_name_are_told_apart() -> None:
    """"AMD EPYC" named two CPU generations in the campaign (families 26 and 25) whose step rates differ: the
    budget table and statement give the family and model a run recorded, and a GPU run is named by its GPU."""
    from gns_bench.report.cells import budget_statement, machines
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import budget_row

    sweep = load_sweep(SWEEPS_DIR / "domains" / "goop.toml")
    planned = sweep.plan("smoke")[0]

    def row(run_id: str, tags: dict[str, str]) -> RunRow:
        metrics = {"test/rollout_mse": 1e-3, "train/wall_time_s": 600.0, "train/final_step": 20.0}
        return RunRow(planned, tracking.RunRecord(run_id, planned.name, "FINISHED", 0, {"train.steps": "20"},
                                                  metrics, {"hardware": "AMD EPYC, 2 threads", **tags}))

    zen5 = row("a", {"device": "cpu", "cpu": "family 26, model 2, stepping 1, 2596 MHz"})
    zen4 = row("b", {"device": "cpu", "cpu": "family 25, model 17, stepping 1, 2596 MHz"})
    untagged = row("c", {})  # runs from before the `cpu` tag
    gpu = row("d", {"device": "cuda", "hardware": "NVIDIA H200", "cpu": "family 25, model 17"})
    assert machines([zen4]) == "AMD EPYC, 2 threads (CPU family 25, model 17)"
    assert machines([zen5, zen4, zen5, untagged, gpu]) == (
        "AMD EPYC, 2 threads (CPU family 25, model 17: 1 run; family 26, model 2: 2 runs; not recorded: 1 run); "
        "NVIDIA H200")
    assert machines([untagged]) == "AMD EPYC, 2 threads" and machines([gpu]) == "NVIDIA H200"
    assert budget_row(sweep, [zen4])[4] == "AMD EPYC, 2 threads (CPU family 25, model 17)"
    assert "(CPU family 25, model 17: 1 run; family 26, model 2: 1 run)" in budget_statement([zen5, zen4])


def test_the_baseline_printed_is_the_one_divided_by() -> None:
    """A ratio is printed beside the two numbers it divides; a stopped rollout is compared with constant
    velocity over the same steps or not at all."""
    from gns_bench.report.cells import budget_statement
    from gns_bench.report.collect import RunRow

    planned = load_sweep(SWEEPS_DIR / "domains" / "goop.toml").plan("smoke")[0]

    def row(rollout: float, constant_velocity: float, stopped: float = 0.0,
            same_steps: float | None = None) -> RunRow:
        metrics = {"test/rollout_mse": rollout, "test/baseline_cv_rollout_mse": constant_velocity,
                   "test/rollout_stopped": stopped, "train/final_step": 20.0, "train/wall_time_s": 60.0}
        if same_steps is not None:
            metrics["test/baseline_cv_same_steps_mse"] = same_steps
        return RunRow(planned, tracking.RunRecord("r", planned.name, "FINISHED", 0, {"train.steps": "20"}, metrics))

    goop = load_sweep(SWEEPS_DIR / "domains" / "goop.toml")
    assert accuracy_row(goop, [row(1.0, 4.0)], True)[11] == "0.25x (1 / 4)"
    assert accuracy_row(goop, [row(1.0, 4.0, stopped=0.2)], True)[11] == "GNS rollouts stopped"
    # the ratio takes both MSEs from the runs whose baseline covers their own steps
    assert accuracy_row(goop, [row(1.0, 2.0), row(9.0, 8.0, stopped=0.2)], True)[11] == "0.5x (1 / 2)"
    stopped = accuracy_row(goop, [row(1.0, 4.0, stopped=0.2, same_steps=0.5)], True)
    assert stopped[11] == "2x (1 / 0.5), over the steps before the stops"
    assert stopped[10] == "— (rollouts stopped)"  # no ratio to the paper's whole-rollout MSE from stopped ones
    text = budget_statement([row(1.0, 4.0, stopped=0.2, same_steps=0.5), row(1.0, 2.0)], "small")
    assert "20 training steps" in text and "h of training in all" in text and "same steps" in text
    assert "own solvers" not in text  # no dataset tier: an imported dataset
    assert budget_statement([row(1.0, 2.0)], "smoke").startswith("**Smoke tier: a pipeline check")


def test_ablation_table_compares_stopped_runs_with_constant_velocity_over_their_own_steps(tmp_path: Path) -> None:
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import ablation_section

    sweep = load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml")
    planned = {r.axes["train.noise_std"]: r for r in sweep.plan("smoke")}

    def row(value: float, rollout: float, same_steps: float, steps: float, stopped: float) -> RunRow:
        metrics = {"test/rollout_mse": rollout, "test/baseline_cv_rollout_mse": 9.0, "test/one_step_mse": 1e-8,
                   "test/baseline_cv_same_steps_mse": same_steps, "test/rollout_steps": steps,
                   "test/rollout_stopped": stopped, "test/ot": 1e-3, "test/mmd": 1e-2}
        return RunRow(planned[value], tracking.RunRecord("r", "n", "FINISHED", 0, {"train.steps": "20"}, metrics))

    # noise 0 covers fewer steps with a lower MSE, but is worse than constant velocity over those steps
    text = "\n".join(ablation_section(sweep, [row(0.0, 0.1, 0.05, 40, 0.8), row(3e-4, 0.3, 0.6, 100, 0.0)],
                                      tmp_path))
    rows = {r[0]: r for r in table_rows(text, "0") + table_rows(text, "0.0003")}
    assert rows["0"][6:8] == ["40 (80% stopped)", "2x (0.1 / 0.05)"]
    assert rows["0.0003"][6:8] == ["100", "0.5x (0.3 / 0.6)"]
    assert "cover different steps" in text


def test_the_rollout_pictures_say_when_the_run_drawn_is_not_the_best_like_for_like() -> None:
    """The pictures are of the lowest raw rollout MSE; a run whose rollouts a monitor stopped early reads low
    there, so the report names the run that is best against constant velocity over the same steps."""
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import _fairer_pick

    sweep = load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml")
    planned = {r.axes["train.noise_std"]: r for r in sweep.plan("smoke")}

    def row(value: float, rollout: float, same_steps: float, steps: float) -> RunRow:
        metrics = {"test/rollout_mse": rollout, "test/baseline_cv_same_steps_mse": same_steps,
                   "test/rollout_steps": steps, "test/rollout_stopped": float(steps < 100)}
        return RunRow(planned[value], tracking.RunRecord(f"run{value}", "n", "FINISHED", 0, {}, metrics))

    stopped, fair = row(0.0, 0.1, 0.05, 40), row(3e-4, 0.3, 0.6, 100)  # lower raw MSE, worse like for like
    (warning, _) = _fairer_pick(stopped, [stopped, fair])
    assert f"{fair.planned.name} (`run0.0003`) reaches 0.5x" in warning and "reaches 2x where" in warning
    assert "covered 40 and 100 steps" in warning
    assert _fairer_pick(fair, [fair, stopped]) == []  # the run drawn is the best like for like: nothing to say


def test_a_run_drawn_in_another_report_is_linked_not_drawn_again(tmp_path: Path) -> None:
    """Issue #20.6: the rollout pictures of a training run live in one report; a report whose best run is
    that run (a shared copy, or the run copies were made from) links them, whichever report drew them."""

    from gns_bench.report.collect import RunRow
    from gns_bench.report.kept import write_kept
    from gns_bench.report.report import _shared_pictures

    drew = tmp_path / "domain-goop" / "cpu"
    drew.mkdir(parents=True)
    (drew / "rollout_best.png").write_bytes(b"png")
    shown = [{"label": "best", "trajectory": 3, "mse": 0.01, "steps": 394, "stopped": ""}]
    write_kept(drew, "domain-goop", "cpu", {"rollouts": {"run_id": "copy1", "source_run": "trained", "split": "test",
                                                         "shown": shown}})
    planned = load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml").plan("cpu")[0]

    def row(run_id: str, tags: dict) -> RunRow:
        return RunRow(planned, tracking.RunRecord(run_id, planned.name, "FINISHED", 0, tags=tags))

    here = tmp_path / "ablation-noise_std" / "cpu"
    copy = row("copy2", {"shared_from": "trained", "shared_from_run": "ablation-connectivity_radius/x"})
    lines = _shared_pictures(copy, here)
    assert "![best rollout](../../domain-goop/cpu/rollout_best.png)" in lines
    assert "which ablation-connectivity_radius trained" in lines[0]
    assert _shared_pictures(row("trained", {}), here)  # the run the copies came from links them too
    assert _shared_pictures(row("other", {}), here) == []  # a run nobody drew: drawn here
    assert _shared_pictures(copy, drew) == []  # never a link to itself


def test_an_ablation_cell_shows_a_spread_only_where_there_are_two_seeds() -> None:
    assert mean_cell(0.0101, 0.000372, 2) == "0.0101 ± 0.000372"
    assert mean_cell(0.0638, 0.0, 1) == "0.0638"  # one seed has no spread: not "± 0"
    assert mean_cell(float("nan"), float("nan"), 0) == "**missing**"


def test_the_rollout_steps_cell_shows_the_spread_over_seeds() -> None:
    from gns_bench.report.cells import steps_covered
    from gns_bench.report.collect import RunRow

    planned = load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml").plan("cpu")[0]

    def row(steps: float, stopped: float) -> RunRow:
        metrics = {"test/rollout_steps": steps, "test/rollout_stopped": stopped}
        return RunRow(planned, tracking.RunRecord("r", "n", "FINISHED", 0, {}, metrics))

    # the default noise's three seeds in the cpu campaign: sample std 58.9 (n - 1)
    assert steps_covered([row(122, 0.8), row(236, 0.8), row(153, 0.8)]) == "170 ± 59 (80% stopped)"
    assert steps_covered([row(92, 1.0)]) == "92 (100% stopped)"  # one seed: no spread to show
    assert steps_covered([row(300, 0.0), row(300, 0.0)]) == "300"  # all over the whole horizon: nothing to show


def test_a_verdict_from_a_sweep_still_training_says_how_many_runs_it_rests_on() -> None:
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import verdict_lines

    sweep = load_sweep(SWEEPS_DIR / "ablations" / "message_passing_steps.toml")
    planned = sweep.plan("cpu")
    assert len(planned) == 5  # M = 1 and 5, and the default 10 at three seeds

    def row(run, rollout: float) -> RunRow:
        metrics = {"test/rollout_mse": rollout, "test/baseline_cv_same_steps_mse": 1.0, "test/rollout_stopped": 0.0}
        return RunRow(run, tracking.RunRecord("r", run.name, "FINISHED", 0, {}, metrics))

    errors = {1: 0.8, 5: 0.3, 10: 0.35}
    reference = ablation_reference("model.message_passing_steps")
    partway = [row(r, errors[r.axes["model.message_passing_steps"]]) if i < 3 else RunRow(r, None)
               for i, r in enumerate(planned)]
    (line,) = verdict_lines("model.message_passing_steps", partway, reference)  # no rollout stopped: one verdict
    assert "So far: from 3 of the 5 planned runs" in line
    done = [row(r, errors[r.axes["model.message_passing_steps"]]) for r in planned]
    assert "So far" not in verdict_lines("model.message_passing_steps", done, reference)[0]


def test_where_monitors_stopped_rollouts_a_second_verdict_judges_how_long_they_ran() -> None:
    # The noise-0 case of the cpu campaign: every rollout collapsed after about half the default's steps, while
    # its error against constant velocity over those few steps matched the default's.
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import verdict_lines

    axis = "train.noise_std"
    planned = load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml").plan("cpu")
    steps = {0.0: [92.0], 3e-4: [170.0, 160.0, 180.0], 3e-3: [117.0]}

    def row(run, i: int) -> RunRow:
        value = run.axes[axis]
        key = next(k for k in steps if abs(k - value) < 1e-12)
        metrics = {"test/rollout_mse": 0.3, "test/baseline_cv_same_steps_mse": 1.0, "test/rollout_stopped": 1.0,
                   "test/rollout_steps": steps[key][i % len(steps[key])], "test/one_step_mse": 1e-8}
        return RunRow(run, tracking.RunRecord(f"r{i}", run.name, "FINISHED", 0, {}, metrics))

    rows = [row(r, i) for i, r in enumerate(planned)]
    assert sorted(r.planned.axes[axis] for r in rows).count(3e-4) == 3
    error, _, length, _, one_step = verdict_lines(axis, rows, ablation_reference(axis))
    assert "inconclusive" in error  # every rollout stopped, where unknown: no common horizon to compare errors on
    assert length.startswith(f"**Verdict on rollout length ({axis}): reproduced.**")
    assert "0.0003 vs 0.0: 1.8x [" in length and "(as the paper; 3 vs 1 seeds, pooled t)" in length  # 170 vs 92
    assert "0.0003 vs 0.003: 1.5x [" in length
    unstopped = [RunRow(r.planned, tracking.RunRecord("u", r.planned.name, "FINISHED", 0, {},
                                                      {**r.record.metrics, "test/rollout_stopped": 0.0}))
                 for r in rows]
    assert "inconclusive" in one_step  # equal one-step errors (the third verdict below)
    lines = verdict_lines(axis, unstopped, ablation_reference(axis))
    assert len(lines) == 3 and not any("rollout length" in line for line in lines)  # nothing stopped: no length verdict


def test_where_the_paper_states_a_one_step_direction_a_verdict_judges_the_one_step_error() -> None:
    # The noise sweep's one-step MSE in the cpu campaign (Intel Xeon family 6 model 207 and AMD EPYC runs): the
    # default's three seeds 7.62e-9, 6.38e-9 and 7.52e-9 (band x1.2), ten times the noise 9.41e-8; no noise 7.34e-9.
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import verdict_lines

    axis = "train.noise_std"
    one_step = {0.0: [7.34e-9], 3e-4: [7.62e-9, 6.38e-9, 7.52e-9], 3e-3: [9.41e-8]}

    def rows(values: dict[float, list[float]]) -> list[RunRow]:
        out = []
        for i, run in enumerate(load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml").plan("cpu")):
            key = next(k for k in values if abs(k - run.axes[axis]) < 1e-12)
            metrics = {"test/rollout_mse": 0.3, "test/baseline_cv_same_steps_mse": 1.0, "test/rollout_stopped": 0.0,
                       "test/one_step_mse": values[key][run.seed % len(values[key])]}
            out.append(RunRow(run, tracking.RunRecord(f"r{i}", run.name, "FINISHED", 0, {}, metrics)))
        return out

    reference = ablation_reference(axis)
    _, _, line = verdict_lines(axis, rows(one_step), reference)
    assert line.startswith(f"**Verdict on the one-step error ({axis}): reproduced.**")
    assert "0.0003 vs 0.003: 0.076x [" in line and "(as the paper; 3 vs 1 seeds, pooled t)" in line
    assert "vs 0.0:" not in line  # the paper states no one-step direction between no noise and the optimum
    _, _, reversed_line = verdict_lines(axis, rows({**one_step, 3e-3: [1e-9]}), reference)
    assert "contradicted" in reversed_line
    sharing = load_sweep(SWEEPS_DIR / "ablations" / "processor_sharing.toml")
    shared_rows = [RunRow(run, tracking.RunRecord("s", run.name, "FINISHED", 0, {}, {
        "test/rollout_mse": 0.3, "test/baseline_cv_same_steps_mse": 1.0, "test/rollout_stopped": 0.0,
        "test/one_step_mse": 1e-8 * (1 + run.seed)})) for run in sharing.plan("cpu")]
    assert len(verdict_lines("model.shared_processor", shared_rows, ablation_reference("model.shared_processor"))) == 1


def test_where_monitors_stopped_rollouts_the_ablation_figure_adds_like_for_like_panels() -> None:
    # the raw rollout MSE of a run whose rollouts collapsed early reads low (noise 0 in the cpu campaign: 0.00455
    # over 92 steps against the default's 0.0131 over 170); its ratio to constant velocity does not
    from gns_bench.report.collect import RunRow
    from gns_bench.report.figures import PANELS, STOPPED_PANELS
    from gns_bench.report.report import ablation_stats

    axis = "train.noise_std"
    planned = [r for r in load_sweep(SWEEPS_DIR / "ablations" / "noise_std.toml").plan("cpu")
               if r.axes[axis] in (0.0, 3e-4)]

    def row(run, stopped: float) -> RunRow:
        zero = run.axes[axis] == 0.0
        metrics = {"test/rollout_mse": 0.00455 if zero else 0.0131, "test/one_step_mse": 7e-9, "test/ot": 0.01,
                   "test/mmd": 0.05, "test/baseline_cv_same_steps_mse": 0.0133 if zero else 0.0413,
                   "test/rollout_steps": 92.0 if zero else 170.0, "test/rollout_stopped": stopped}
        return RunRow(run, tracking.RunRecord("r", run.name, "FINISHED", 0, {}, metrics))

    rows = [row(r, 0.8) for r in planned]
    stats = ablation_stats(axis, [0.0, 3e-4], rows, like_for_like=True)
    assert list(stats) == [m for m, _ in PANELS[:2] + STOPPED_PANELS + PANELS[2:]]
    assert stats["rollout_mse"][0][0] < stats["rollout_mse"][1][0]  # the raw error favours the early collapse
    assert [s[0] for s in stats["vs_cv"]] == pytest.approx([0.00455 / 0.0133, 0.0131 / 0.0413])
    assert [s[0] for s in stats["rollout_steps"]] == [92.0, 170.0] and stats["rollout_steps"][1][2] == 3
    assert list(ablation_stats(axis, [0.0, 3e-4], rows, like_for_like=False)) == [m for m, _ in PANELS]


def test_a_little_difference_verdict_needs_equivalence_on_two_seeds_a_side() -> None:
    # App. C.1's MLP depth: one seed at depth 1 near the default's three is not enough to call "little difference"
    # reproduced (equivalence needs two seeds a side); a tenfold error contradicts it; the rule is stated.
    from gns_bench.report.collect import RunRow
    from gns_bench.report.report import VERDICT_RULES, verdict_lines

    def rows(axis: str, sweep: str, error: dict) -> list[RunRow]:
        out = []
        for i, run in enumerate(load_sweep(SWEEPS_DIR / "ablations" / f"{sweep}.toml").plan("cpu")):
            ratio = error.get(run.axes[axis], [0.32, 0.28, 0.36][run.seed % 3])
            metrics = {"test/rollout_mse": ratio, "test/baseline_cv_same_steps_mse": 1.0, "test/rollout_stopped": 0.0}
            out.append(RunRow(run, tracking.RunRecord(f"r{i}", run.name, "FINISHED", 0, {}, metrics)))
        return out

    depth = "model.mlp_hidden_layers"
    lines = verdict_lines(depth, rows(depth, "mlp_depth", {1: 0.29}), ablation_reference(depth))
    assert lines[0].startswith(f"**Verdict ({depth}): inconclusive.**")
    assert "one seed: equivalence needs two a side" in lines[0]
    far = verdict_lines(depth, rows(depth, "mlp_depth", {1: 3.0}), ablation_reference(depth))
    assert far[0].startswith(f"**Verdict ({depth}): contradicted.**")  # beyond the margin: the claim fails
    assert "equivalence test" in VERDICT_RULES and "1.25x" in VERDICT_RULES
    steps = "model.message_passing_steps"
    directional = verdict_lines(steps, rows(steps, "message_passing_steps", {1: 0.8, 5: 0.4}),
                                ablation_reference(steps))
    assert not any("one seed: equivalence" in line for line in directional)
