"""Test-wide settings: one BLAS thread per process (CI has 2 cores), the project root on sys.path."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

NUMPROJECT = Path(__file__).resolve().parent / "numproject"


@pytest.fixture
def numproject(tmp_path):
    """A fresh copy of the small numeric test project; returns its directory."""
    dest = tmp_path / "proj"
    shutil.copytree(NUMPROJECT, dest, ignore=shutil.ignore_patterns("__pycache__", ".msflow", "*.lock"))
    return dest


def cli_env(env=None):
    """Environment for msflow subprocesses: this checkout first on PYTHONPATH, whichever checkout
    `pip install -e` last pointed at."""
    full_env = dict(os.environ)
    full_env.update(env or {})
    full_env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), full_env.get("PYTHONPATH", "")) if p)
    return full_env


def run_cli(cwd, *args, env=None, timeout=120):
    """Run ``python -m msflow.cli`` in a subprocess; returns CompletedProcess with text output."""
    return subprocess.run(
        [sys.executable, "-m", "msflow.cli", *map(str, args)],
        cwd=cwd,
        env=cli_env(env),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def executions(log_path):
    """Stage names executed, in order, from a NUMSTAGES_LOG side channel."""
    path = Path(log_path)
    return [line.split()[0] for line in path.read_text().splitlines()] if path.exists() else []


@pytest.fixture(scope="session")
def default_run(tmp_path_factory):
    """The repository's default pipeline, run once per session in a copy with its own store."""
    import msflow

    dest = tmp_path_factory.mktemp("repo") / "msflow"
    dest.mkdir()
    for name in ("pipeline.yaml", "data", "stages", "pyproject.toml"):
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(src, dest / name)
    return dest, msflow.run(dest / "pipeline.yaml")
