"""The Dask executor: same keys and results as local runs, a worker dying mid-stage is retried."""

import shutil

import numpy as np
from conftest import executions, run_cli

import msflow


def test_dask_gives_the_same_keys_and_content_as_local(numproject, tmp_path, monkeypatch):
    local = msflow.run(numproject / "pipeline.yaml")
    clone = tmp_path / "dask"
    shutil.copytree(numproject, clone, ignore=shutil.ignore_patterns(".msflow"))
    log = tmp_path / "log"
    monkeypatch.setenv("NUMSTAGES_LOG", str(log))
    remote = msflow.run(clone / "pipeline.yaml", executor="dask", jobs=2)
    assert remote.record["executor"] == "dask" and sorted(remote.executed) == sorted(local.states)
    for name in local.states:
        assert remote.key(name) == local.key(name)
        assert remote.states[name].manifest["content_hash"] == local.states[name].manifest["content_hash"]
    import os

    assert str(os.getpid()) not in {line.split()[1] for line in log.read_text().splitlines()}


def test_worker_killed_mid_stage_is_retried_without_partial_artifacts(numproject, tmp_path, monkeypatch):
    marker = tmp_path / "attempted"
    log = tmp_path / "log"
    monkeypatch.setenv("NUMSTAGES_MARKER", str(marker))
    monkeypatch.setenv("NUMSTAGES_LOG", str(log))
    result = msflow.run(numproject / "dieonce.yaml", executor="dask", jobs=1)
    assert marker.exists()  # the first attempt died
    assert result.states["die"].state == "ran" and executions(log).count("die") == 1
    assert np.allclose(result.load("die.y"), np.arange(5.0) + 1)
    assert run_cli(numproject, "verify", "dieonce.yaml").returncode == 0
    tmp = numproject / ".msflow" / "tmp"
    assert not tmp.exists() or not any(tmp.iterdir())


def test_sweep_on_dask_matches_local(numproject, tmp_path):
    from msflow.sweep import expand_variants, run_sweep

    variants = expand_variants(["src.n=3,4"], None)
    local = run_sweep(numproject / "pipeline.yaml", variants)
    clone = tmp_path / "dask"
    shutil.copytree(numproject, clone, ignore=shutil.ignore_patterns(".msflow"))
    remote = run_sweep(clone / "pipeline.yaml", variants, executor="dask", jobs=2)
    assert [v.metrics for v in remote.variants] == [v.metrics for v in local.variants]
    assert remote.executed == local.executed


def test_unreachable_scheduler_is_a_clear_error(numproject):
    result = run_cli(
        numproject, "run", "--scheduler", "tcp://127.0.0.1:9", "--connect-timeout", "1.5", "--force", "src"
    )
    assert result.returncode == 2
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9 within 1.5s" in result.stderr
    assert "Traceback" not in result.stderr
