"""Crash and concurrency safety: SIGKILL at any moment, concurrent runs, dead lock holders, corruption."""

import json
import random
import signal
import subprocess
import sys
import time

import numpy as np
from conftest import cli_env, executions, run_cli

from msflow.artifact import read_manifest


def start_run(proj, *args, env):
    return subprocess.Popen(
        [sys.executable, "-m", "msflow.cli", "run", *args, "-q"],
        cwd=proj,
        env=cli_env(env),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def visible_artifacts(proj):
    root = proj / ".msflow" / "artifacts"
    return [p for p in root.glob("*/*")] if root.exists() else []


def test_sigkill_at_any_moment_leaves_no_partial_artifact_and_next_run_recovers(numproject, tmp_path):
    rng = random.Random(1234)
    log = tmp_path / "log"
    env = {"NUMSTAGES_LOG": str(log), "NUMSTAGES_SLEEP": "0.3"}
    for attempt in range(7):
        proc = start_run(numproject, "crash.yaml", "--force", "slow", env=env)
        time.sleep(rng.uniform(0.25, 1.6))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        for artifact in visible_artifacts(numproject):  # whatever is visible is complete
            manifest = read_manifest(artifact)
            assert set(manifest["outputs"]) <= {p.name for p in artifact.iterdir()}
    result = run_cli(numproject, "run", "crash.yaml", "-q", env={"NUMSTAGES_SLEEP": "0"})
    assert result.returncode == 0, result.stderr
    verify = run_cli(numproject, "verify", "crash.yaml")
    assert verify.returncode == 0 and "0 corrupt" in verify.stdout, verify.stdout
    import msflow

    out = msflow.run(numproject / "crash.yaml")
    assert out.executed == []
    big = out.load("slow.big")
    assert np.array_equal(big, np.random.default_rng(7).standard_normal(3_000_000))
    assert out.load("after.total") == np.float64(big.sum() + 45)
    leftovers = list((numproject / ".msflow" / "tmp").iterdir()) if (numproject / ".msflow" / "tmp").exists() else []
    assert leftovers == []


def test_two_concurrent_runs_execute_each_stage_exactly_once(numproject, tmp_path):
    log = tmp_path / "log"
    env = {"NUMSTAGES_LOG": str(log), "NUMSTAGES_SLEEP": "1.0"}
    procs = [start_run(numproject, "crash.yaml", env=env) for _ in range(3)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], outs
    ran = executions(log)
    assert sorted(ran) == ["after", "scaled", "slow", "src"]
    records = [json.loads(p.read_text()) for p in (numproject / ".msflow" / "runs").glob("*.json")]
    assert len(records) == 3
    for stage in ("slow", "after", "src", "scaled"):
        assert sum(r["stages"][stage]["state"] == "ran" for r in records) == 1


def test_lock_held_by_a_killed_run_is_broken(numproject, tmp_path):
    env = {"NUMSTAGES_SLEEP": "30"}
    proc = start_run(numproject, "crash.yaml", "--until", "slow", env=env)
    locks = numproject / ".msflow" / "locks"
    deadline = time.time() + 30
    while time.time() < deadline and not (locks.exists() and any(locks.iterdir())):
        time.sleep(0.05)
    time.sleep(0.5)  # the holder is now inside the stage, holding the key's lock
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    started = time.time()
    result = run_cli(numproject, "run", "crash.yaml", "--until", "slow", "-q", env={"NUMSTAGES_SLEEP": "0"}, timeout=60)
    assert result.returncode == 0, result.stderr
    assert time.time() - started < 30


def test_verify_detects_a_flipped_byte_in_a_stored_chunk(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert run_cli(numproject, "verify").returncode == 0
    chunks = sorted(p for p in (numproject / ".msflow" / "artifacts").rglob("c/*") if p.is_file())
    victim = max(chunks, key=lambda p: p.stat().st_size)
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0x40
    victim.write_bytes(bytes(data))
    key = victim.relative_to(numproject / ".msflow" / "artifacts").parts[1]
    result = run_cli(numproject, "verify")
    assert result.returncode == 1
    assert f"corrupt {key}" in result.stdout and "1 corrupt" in result.stdout
    fixed = run_cli(numproject, "verify", "--delete")
    assert fixed.returncode == 1 and "removed" in fixed.stdout
    rerun = run_cli(numproject, "run", "-q")  # the removed artifact is recomputed
    assert rerun.returncode == 0
    assert run_cli(numproject, "verify").returncode == 0
