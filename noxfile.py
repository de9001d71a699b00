"""nox sessions. Each installs the package with the shared constraints file (torch pinned first).

    nox -s tests              the fast suite (what CI runs)
    nox -s tests -- slow      the slow tests only
    nox -s lint               ruff
    nox -s quickstart         tiny dataset -> train -> evaluate, in MLflow
    nox -s ui                 the MLflow UI on 127.0.0.1
    nox -s report -- SWEEP    a sweep's report from MLflow (markdown + PNG) into reports/
    nox -s bench              the speed benchmark into reports/bench/
    nox -s device             on a lent GPU: CUDA tests, GPU benchmark, 4 runs at once (reports/bench/<gpu>/)
    nox -s <sweep> -- TIER    one session per sweep file (sweeps/**/*.toml), TIER smoke|small|cpu|paper
                              e.g. nox -s ablation-noise_std -- small; `nox -l` lists them
    nox -s campaign-paper -- TIER   every sweep of sweeps/campaigns/paper.toml in order, then every report
"""

from __future__ import annotations

import importlib.util
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
        session.error("usage: nox -s report -- SWEEP|domains|stability|index|all [--tier smoke|small|cpu|paper]")
    session.run("gns-bench", "report", *session.posargs)


@nox.session
def bench(session: nox.Session) -> None:
    """nox -s bench [-- --quick]: the speed benchmark into reports/bench/ (and MLflow)."""
    install(session)
    session.run("gns-bench", "bench", *session.posargs)


@nox.session(venv_backend="none")
def device(session: nox.Session) -> None:
    """nox -s device: on a lent GPU, the checks of gns_bench/bench/device.py (CUDA tests, the benchmark on the
    GPU, 4 runs at once) into reports/bench/<gpu>/, in the environment at hand: such machines may reach no
    package index, so nothing is installed (that module's docstring lists what must be there)."""
    session.run(sys.executable, "-m", "gns_bench.bench.device", *session.posargs, external=True)


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


def _tier_session(command: str, path: Path, doc: str):
    """A session that runs `gns-bench COMMAND PATH --tier TIER [options]` in the shared sweep environment."""
    def session(session: nox.Session) -> None:
        bin_dir = shared_sweep_env(session)
        tier = session.posargs[0] if session.posargs else "smoke"
        session.run(str(bin_dir / "gns-bench"), command, str(path), "--tier", tier, *session.posargs[1:],
                    external=True)

    session.__doc__ = doc
    return session


# One session per sweep file, named as gns-bench names the sweep: gns_bench/sweep/naming.py, loaded by path
# (this file runs before gns_bench is installed). A new TOML is a new session; nothing here changes.
_spec = importlib.util.spec_from_file_location("sweep_naming", Path("gns_bench/sweep/naming.py"))
_naming = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_naming)
for _path in sorted(Path("sweeps").rglob("*.toml")):
    if not _naming.is_sweep_file(_path, Path("sweeps")):
        continue
    _name = _naming.sweep_name(_path, Path("sweeps"))
    nox.session(name=_name, venv_backend="none")(
        _tier_session("sweep", _path, f"sweep {_path} (posargs: TIER [gns-bench sweep options])"))


# One session per campaign file: sweeps/campaigns/paper.toml -> campaign-paper.
for _path in sorted(Path("sweeps/campaigns").glob("*.toml")):
    nox.session(name=f"campaign-{_path.stem}", venv_backend="none")(_tier_session(
        "campaign", _path, f"campaign {_path}: its sweeps in order, then every report (posargs: TIER [options])"))
