"""nox sessions. Each installs the package with the shared constraints file (torch pinned first).

    nox -s tests              the fast suite (what CI runs)
    nox -s tests -- slow      the slow tests only
    nox -s lint               ruff
    nox -s quickstart         tiny dataset -> train -> evaluate, in MLflow
    nox -s ui                 the MLflow UI on 127.0.0.1
    nox -s report -- SWEEP    a sweep's report from MLflow (markdown + PNG) into reports/
    nox -s bench              the speed benchmark into reports/bench/
    nox -s <sweep> -- TIER    one session per sweep file (sweeps/**/*.toml), TIER smoke|small|paper
                              e.g. nox -s ablation-noise_std -- small; `nox -l` lists them
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import nox

nox.options.sessions = ["lint", "tests"]
nox.options.reuse_existing_virtualenvs = True
CONSTRAINTS = os.environ.get("GNS_BENCH_CONSTRAINTS", "constraints.txt")


def install(session: nox.Session, extras: str = "dev") -> None:
    session.install("-c", CONSTRAINTS, "torch")
    session.install("-c", CONSTRAINTS, "-e", f".[{extras}]")


@nox.session
def tests(session: nox.Session) -> None:
    install(session)
    if session.posargs[:1] == ["slow"]:
        session.run("pytest", "-m", "slow", *session.posargs[1:])
    else:
        session.run("pytest", *session.posargs)


@nox.session
def lint(session: nox.Session) -> None:
    session.install("ruff")
    session.run("ruff", "check", "gns_bench", "tests", "noxfile.py")


@nox.session
def quickstart(session: nox.Session) -> None:
    install(session)
    session.run("gns-bench", "quickstart", *session.posargs)


@nox.session
def report(session: nox.Session) -> None:
    """nox -s report -- SWEEP [--tier T]: the sweep's report from MLflow into reports/."""
    install(session)
    if not session.posargs:
        session.error("usage: nox -s report -- SWEEP|domains|stability|all [--tier smoke|small|paper]")
    session.run("gns-bench", "report", *session.posargs)


@nox.session
def bench(session: nox.Session) -> None:
    """nox -s bench [-- --quick]: the speed benchmark into reports/bench/ (and MLflow)."""
    install(session)
    session.run("gns-bench", "bench", *session.posargs)


@nox.session
def ui(session: nox.Session) -> None:
    install(session)
    session.run("gns-bench", "ui", *session.posargs)


SWEEP_ENV = Path(".nox") / "sweeps-shared"


def shared_sweep_env(session: nox.Session) -> Path:
    """One environment for all sweep sessions (28 of them need the same packages), installed once and
    again whenever pyproject.toml or the constraints change. Returns its bin folder."""
    stamp = SWEEP_ENV / "installed.stamp"
    sources = [Path("pyproject.toml"), Path(CONSTRAINTS)]
    bin_dir = SWEEP_ENV / "bin"
    if not stamp.exists() or any(p.stat().st_mtime > stamp.stat().st_mtime for p in sources):
        session.run(sys.executable, "-m", "venv", str(SWEEP_ENV), external=True)
        pip = [str(bin_dir / "python"), "-m", "pip", "install", "-q", "-c", CONSTRAINTS]
        session.run(*pip, "torch", external=True)
        session.run(*pip, "-e", ".", external=True)
        stamp.write_text("ok\n")
    return bin_dir


def _sweep_session(path: Path):
    def session(session: nox.Session) -> None:
        bin_dir = shared_sweep_env(session)
        tier = session.posargs[0] if session.posargs else "smoke"
        session.run(str(bin_dir / "gns-bench"), "sweep", str(path), "--tier", tier, *session.posargs[1:],
                    external=True)

    session.__doc__ = f"sweep {path} (posargs: TIER [gns-bench sweep options])"
    return session


# One session per sweep file, named as gns-bench names the sweep (gns_bench/sweep/spec.py sweep_name),
# with gns_bench.sweep.spec.SWEEP_PREFIXES copied here (this file runs before gns_bench is installed):
# sweeps/ablations/noise_std.toml -> ablation-noise_std, sweeps/studies/learning_rate_decay.toml ->
# study-learning_rate_decay. A new TOML is a new session; nothing here changes.
SWEEP_PREFIXES = {"domains": "domain", "ablations": "ablation", "stress": "stress", "studies": "study"}
for _path in sorted(Path("sweeps").rglob("*.toml")):
    if _path.name == "tiers.toml":
        continue
    _folder = _path.parent.name if _path.parent != Path("sweeps") else ""
    _plain = _folder[:-1] if _folder.endswith("s") and not _folder.endswith("ss") else _folder
    _prefix = SWEEP_PREFIXES.get(_folder, _plain)
    _name = f"{_prefix}-{_path.stem}" if _prefix else _path.stem
    nox.session(name=_name, venv_backend="none")(_sweep_session(_path))
