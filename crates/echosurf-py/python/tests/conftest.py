"""Shared fixtures: the `echosurf` CLI (the reference every test compares against) and the sweeps it
simulates, each made once per session in a temporary folder."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[4]


def cli_path() -> Path:
    """The CLI binary: $ECHOSURF_BIN (`.ci/run` sets it), else target/debug/echosurf of this repo."""
    given = os.environ.get("ECHOSURF_BIN")
    path = Path(given) if given else REPO / "target" / "debug" / "echosurf"
    if not path.is_file():
        pytest.fail(
            f"the echosurf CLI is not at {path}: build it (cargo build -p echosurf-cli) or set "
            "ECHOSURF_BIN to its path",
            pytrace=False,
        )
    return path


def run_cli(*args: object) -> subprocess.CompletedProcess:
    """Runs the CLI; fails the test with its stderr when it exits non-zero."""
    command = [str(cli_path()), *(str(a) for a in args)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        pytest.fail(f"{' '.join(command)} exited {done.returncode}:\n{done.stderr}", pytrace=False)
    return done


@pytest.fixture(scope="session")
def cli():
    return run_cli


@pytest.fixture(scope="session")
def duck(tmp_path_factory) -> "tuple[Path, Path]":
    """The demo's sweep: `echosurf simulate` of the duck phantom with the demo's settings (seed 1;
    the same bytes as the `duck.mha` that `echosurf demo` writes)."""
    folder = tmp_path_factory.mktemp("duck")
    run_cli("simulate", "--out", folder, "--name", "duck", "--seed", 1)
    return folder / "duck.mha", folder / "duck_config.xml"


@pytest.fixture(scope="session")
def sphere(tmp_path_factory) -> "tuple[Path, Path]":
    """A small sphere sweep (20 frames of 96 x 80 px), quick to extract."""
    folder = tmp_path_factory.mktemp("sphere")
    run_cli(
        "simulate", "--phantom", "sphere", "--seed", 3, "--frames-per-sweep", 20,
        "--width", 96, "--height", 80, "--pixel-size", 0.4, "--out", folder,
    )
    return folder / "sim.mha", folder / "sim_config.xml"
