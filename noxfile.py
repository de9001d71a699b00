"""nox sessions. Each installs the package with the shared constraints file (torch pinned first).

    nox -s tests              the fast suite (what CI runs)
    nox -s tests -- slow      the slow tests only
    nox -s lint               ruff
    nox -s quickstart         tiny dataset -> train -> evaluate, in MLflow
    nox -s ui                 the MLflow UI on 127.0.0.1
"""

from __future__ import annotations

import os

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
def ui(session: nox.Session) -> None:
    install(session)
    session.run("gns-bench", "ui", *session.posargs)
