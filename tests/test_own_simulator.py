"""A simulator of one's own (examples/particle_mlp.py), registered from outside gns_bench/, is trained,
evaluated, swept, reloaded and reported exactly as the GNS is."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from gns_bench import simulators
from gns_bench.config import ConfigError, load_config
from gns_bench.report import baselines, report
from gns_bench.sweep.runner import run_sweep
from gns_bench.sweep.spec import SWEEPS_DIR, load_sweep
from gns_bench.train.checkpoints import load_simulator

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
ARCHITECTURE = "particle_mlp:SPEC"


def test_an_unknown_architecture_is_refused_with_what_is_registered(tmp_path: Path) -> None:
    from gns_bench.data.tiny import generate_tiny
    from gns_bench.pipeline import train_run

    with pytest.raises(ValueError, match="no such simulator; registered: cconv, dpi, gns"):
        simulators.get("mlp")
    with pytest.raises(ValueError, match="cannot import 'SPEC' from 'no_such_module'"):
        simulators.get("no_such_module:SPEC")
    data = generate_tiny(tmp_path / "tiny", "smoke", seed=0)
    with pytest.raises(ConfigError, match="model.architecture = 'mlp': no such simulator"):
        train_run(load_config(None, ["model.architecture=mlp"]), data, tmp_path / "run")
    assert not (tmp_path / "run").exists()  # refused before anything was created


def test_the_example_trains_evaluates_sweeps_and_is_reported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(EXAMPLES))
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    root = tmp_path / "sweeps"
    for folder in ("domains", "baselines"):
        (root / folder).mkdir(parents=True)
    shutil.copy(SWEEPS_DIR / "tiers.toml", root / "tiers.toml")
    (root / "domains" / "tiny.toml").write_text(
        'description = "tiny"\ndomain = "tiny"\n\n[tiers.smoke.config.model]\nlatent_size = 8\n'
        'mlp_hidden_size = 8\nmessage_passing_steps = 1\n')
    (root / "baselines" / "mlp-tiny.toml").write_text(
        'description = "a per-particle MLP on tiny"\ndomain = "tiny"\n'
        f'config.model = {{ architecture = "{ARCHITECTURE}" }}\n'
        'default = { "train.noise_std" = 3e-4 }\n\n[grid]\n"train.noise_std" = [3e-4]\n')
    domain, own = load_sweep(root / "domains" / "tiny.toml"), load_sweep(root / "baselines" / "mlp-tiny.toml")
    for sweep in (domain, own):
        outcomes = run_sweep(sweep, "smoke", data_root=tmp_path / "data", runs_root=tmp_path / "runs", progress=False)
        assert all(o.status == "FINISHED" for o in outcomes), [o.error for o in outcomes]
    # trained and evaluated: test metrics logged, and the checkpoint reloads as the same kind of model
    rows = baselines.collect(own, "smoke", tmp_path / "reports")
    assert rows[0].ok and rows[0].metric("rollout_mse") > 0 and rows[0].metric("one_step_mse") > 0
    (checkpoint,) = [p for p in (tmp_path / "runs").rglob("checkpoint.pt") if "mlp-tiny" in str(p)]
    simulator, config, _ = load_simulator(checkpoint)
    assert type(simulator).__name__ == "ParticleMLP" and config.model.architecture == ARCHITECTURE
    assert simulators.display_name(ARCHITECTURE) == "per-particle MLP"
    # reported beside the GNS under its own name
    monkeypatch.setattr(report, "domain_sweeps", lambda: [domain])
    page = report.write_sweep_report(own, "smoke", tmp_path / "reports" / own.name / "smoke").read_text()
    assert "## per-particle MLP beside the GNS (Sec. 5.5)" in page
    assert "| tiny (particle_mlp:SPEC) |" in page  # its row in the table beside the GNS's
    assert "ground truth beside per-particle MLP on one frame" in page
