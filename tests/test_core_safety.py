"""Crash and concurrency safety: SIGKILL at any moment, concurrent runs, dead lock holders, corruption."""

import json
import signal

import numpy as np
import pytest
from conftest import Hold, executions, run_cli, start_cli, wait_for_line

import msflow
from msflow.artifact import read_manifest


def visible_artifacts(proj):
    root = proj / ".msflow" / "artifacts"
    return [p for p in root.glob("*/*")] if root.exists() else []


def assert_visible_artifacts_complete(proj):
    for artifact in visible_artifacts(proj):  # whatever is visible is complete
        manifest = read_manifest(artifact)
        assert set(manifest["outputs"]) <= {p.name for p in artifact.iterdir()}
    assert run_cli(proj, "verify", "crash.yaml").returncode == 0


@pytest.mark.parametrize("forced", [False, True])
def test_sigkill_while_computing_leaves_nothing_partial_and_the_next_run_recovers(numproject, tmp_path, forced):
    if forced:  # a replacement killed mid-way keeps the artifact it was replacing
        assert run_cli(numproject, "run", "crash.yaml", "--until", "slow", "-q").returncode == 0
    before = {p.name for p in visible_artifacts(numproject)}
    hold = Hold(tmp_path / "hold")
    proc = start_cli(numproject, "run", "crash.yaml", "--force", "slow", "-q", env=hold.env)
    assert hold.wait_ready(proc).startswith("slow ")
    proc.kill()
    proc.wait()
    assert {p.name for p in visible_artifacts(numproject)} == before
    assert_visible_artifacts_complete(numproject)
    result = run_cli(numproject, "run", "crash.yaml", "-q")
    assert result.returncode == 0, result.stderr
    out = msflow.run(numproject / "crash.yaml")
    assert out.executed == []
    big = out.load("slow.big")
    assert np.array_equal(big, np.random.default_rng(7).standard_normal(3_000_000))
    assert out.load("after.total") == np.float64(big.sum() + 45)
    tmp = numproject / ".msflow" / "tmp"
    assert not tmp.exists() or list(tmp.iterdir()) == []


@pytest.mark.parametrize(
    ("jobs", "signum", "code"), [("1", "SIGINT", 130), ("2", "SIGINT", 130), ("2", "SIGTERM", 143)]
)
def test_ctrl_c_says_what_it_kept_and_the_next_run_goes_on(numproject, tmp_path, jobs, signum, code):
    """Ctrl-C (or a SIGTERM: kill, docker stop) in the middle of a stage, sent to msflow alone: it stops at once
    (the pool waited for the stage, a SIGTERM left the workers at work) with a line saying so (typer swallowed
    it silently), no traceback, nothing partial visible, and the next run computes only what was cut short."""
    hold = Hold(tmp_path / "hold")
    proc = start_cli(numproject, "run", "crash.yaml", "-j", jobs, env=hold.env)
    hold.wait_ready(proc)
    proc.send_signal(getattr(signal, signum))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code and "interrupted: what finished is kept" in err, err
    assert "Traceback" not in err, err
    assert_visible_artifacts_complete(numproject)
    tmp = numproject / ".msflow" / "tmp"
    assert not tmp.exists() or list(tmp.iterdir()) == []
    # the run is on record, stopped, with what it had settled (msflow runs listed nothing before)
    listed = run_cli(numproject, "runs", "crash.yaml").stdout.splitlines()
    assert len(listed) == 1 and "  STOPPED  " in listed[0], listed
    record = json.loads(next((numproject / ".msflow" / "runs").glob("*.json")).read_text())
    assert record["interrupted"] is True and record["ok"] is False
    assert record["stages"]["slow"]["state"] == "running"
    report = run_cli(
        numproject, "report", "-f", "crash.yaml", "-o", str(tmp_path / "r.html")
    )  # reports whole runs only
    assert report.returncode == 2 and "no run of this pipeline yet" in report.stderr, report.stderr
    published = {p.name for p in visible_artifacts(numproject)}
    out = msflow.run(numproject / "crash.yaml")
    assert "slow" in out.executed and not {out.key(name) for name in out.executed} & published
    assert np.array_equal(out.load("slow.big"), np.random.default_rng(7).standard_normal(3_000_000))


def test_a_run_waits_for_a_gc_in_progress_saying_so(numproject):
    """gc holds the store alone while it deletes; a run started meanwhile says why it waits and goes on after."""
    import fcntl

    store_lock = numproject / ".msflow" / "locks" / "store.lock"
    store_lock.parent.mkdir(parents=True)
    with store_lock.open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # what msflow gc holds while it deletes
        proc = start_cli(numproject, "run", "-q")
        wait_for_line(proc, "msflow gc is cleaning the store; waiting for it to finish")
        assert proc.poll() is None and not (numproject / ".msflow" / "runs").exists()
        fcntl.flock(held, fcntl.LOCK_UN)
    assert proc.wait(timeout=120) == 0, proc.stderr.read()
    assert len(list((numproject / ".msflow" / "runs").glob("*.json"))) == 1


def test_gc_refuses_while_a_run_is_making_artifacts_no_record_names_yet(numproject, tmp_path):
    """gc keeps what run records name, and a run writes its record at the end: a gc during the run deleted the
    stages it had finished, and the run then recorded them, so the next run and status said "cached" for
    artifacts that were gone. gc now fails while a run holds the store (exit 2, saying why), and works again
    once the run has ended, or has been killed."""
    hold = Hold(tmp_path / "hold")
    proc = start_cli(numproject, "run", "crash.yaml", "-j", "2", env=hold.env)
    hold.wait_ready(proc)
    status = run_cli(numproject, "status", "crash.yaml")  # says that the held stage is being computed (by a worker)
    computing = f"slow    will run\n          - being computed now by a run in progress (pid {proc.pid} on "
    assert computing in status.stdout and ", in its worker " in status.stdout, status.stdout  # the run's pid first
    assert status.stdout.count("being computed now") == 1
    refused = run_cli(numproject, "gc", "crash.yaml")
    assert refused.returncode == 2 and "a run is using the store" in refused.stderr, refused.stderr
    assert "Traceback" not in refused.stderr
    hold.release()
    assert proc.wait(timeout=120) == 0
    done = run_cli(numproject, "gc", "crash.yaml")
    assert done.returncode == 0 and "removed 0 artifacts" in done.stdout, (done.stdout, done.stderr)
    out = msflow.run(numproject / "crash.yaml")
    assert out.executed == [] and out.load("scaled.y").size > 0  # every artifact the record names is there

    (hold.folder / "release").unlink()
    (hold.folder / "ready").unlink()
    killed = start_cli(numproject, "run", "crash.yaml", "--force", "slow", env=hold.env)
    hold.wait_ready(killed)
    killed.kill()
    killed.wait()
    assert run_cli(numproject, "gc", "crash.yaml").returncode == 0  # a dead run holds nothing


def test_two_concurrent_runs_execute_each_stage_exactly_once(numproject, tmp_path):
    log = tmp_path / "log"
    hold = Hold(tmp_path / "hold")
    env = {"NUMSTAGES_LOG": str(log), **hold.env}
    first = start_cli(numproject, "run", "crash.yaml", "-q", env=env)
    hold.wait_ready(first)  # the first run holds the key of 'slow' and is inside the stage
    others = [start_cli(numproject, "run", "crash.yaml", "-q", env=env) for _ in range(2)]
    for proc in others:  # both reach the same key and wait for the first run
        wait_for_line(proc, "stage 'slow' is being computed by another run")
    hold.release()
    outs = [p.communicate(timeout=120) for p in (first, *others)]
    assert [p.returncode for p in (first, *others)] == [0, 0, 0], outs
    ran = executions(log)
    assert sorted(ran) == ["after", "scaled", "slow", "src"]
    records = [json.loads(p.read_text()) for p in (numproject / ".msflow" / "runs").glob("*.json")]
    assert len(records) == 3
    for stage in ("slow", "after", "src", "scaled"):
        assert sum(r["stages"][stage]["state"] == "ran" for r in records) == 1
    assert sum(r["stages"]["slow"]["detail"] == "computed by a concurrent run" for r in records) == 2


@pytest.mark.parametrize("checked", [True, False])
def test_an_artifact_published_while_the_worker_waited_for_the_lock_is_a_concurrent_runs(
    numproject, monkeypatch, checked
):
    """Whether or not the runner checked the store first (Job.checked: it leaves that to the worker for a stage
    whose input it just computed), an artifact that appears while the worker waits for the key's lock was
    computed by the run holding it, and the outcome says so."""
    import threading

    import msflow.worker
    from msflow.jobs import Job, Outcome
    from msflow.stores import open_store

    store = open_store(str(numproject / ".msflow"), {})
    key = "ef" + "5" * 30
    job = Job(str(store.url), {}, str(numproject), key, "src", "numstages.basic:Source", {"n": 3}, {}, checked=checked)
    waiting = threading.Event()
    monkeypatch.setattr(msflow.worker, "report_waiting", lambda stage, holder: waiting.set())
    outcomes = []
    with store.lock(key):
        worker = threading.Thread(
            target=lambda: outcomes.append(Outcome.from_json(msflow.worker.run_job(job.to_json())))
        )
        worker.start()
        assert waiting.wait(60)  # a guard against hanging, not a speed assertion
        store.write(key, {"x": np.arange(3.0)}, {"meta": {}, "metrics": {}})
    worker.join(60)
    assert [(o.status.value, o.concurrent) for o in outcomes] == [("cached", True)]


def test_lock_held_by_a_killed_run_is_broken(numproject, tmp_path):
    hold = Hold(tmp_path / "hold")
    proc = start_cli(numproject, "run", "crash.yaml", "--until", "slow", "-q", env=hold.env)
    hold.wait_ready(proc)  # the holder is inside the stage, holding the key's lock
    proc.kill()
    proc.wait()
    result = run_cli(numproject, "run", "crash.yaml", "--until", "slow", "-q", timeout=60)
    assert result.returncode == 0, result.stderr
    assert "being computed by another run" not in result.stderr  # the dead holder's lock was free at once


def test_verify_detects_a_flipped_byte_and_verify_delete_removes_it_and_exits_0(numproject):
    """Without --delete, a corrupt artifact is exit 1 and the hint to remove it; --delete removes it, says which
    and that a run recomputes it, and exits 0: the corruption was found and dealt with."""
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
    assert f"corrupt {key}" in result.stdout and "1 corrupt; `msflow verify --delete` removes it" in result.stdout
    fixed = run_cli(numproject, "verify", "--delete")
    assert fixed.returncode == 0, fixed.stdout + fixed.stderr
    removed = f"1 corrupt, removed ({key[:12]}); a run that needs it computes it again"
    assert removed in fixed.stdout and "--delete" not in fixed.stdout + fixed.stderr, fixed.stdout
    assert key not in {p.name for p in (numproject / ".msflow" / "artifacts").glob("*/*")}
    assert "0 corrupt" in run_cli(numproject, "verify").stdout
    rerun = run_cli(numproject, "run", "-q")  # the removed artifact is recomputed
    assert rerun.returncode == 0
    assert key in {p.name for p in (numproject / ".msflow" / "artifacts").glob("*/*")}
    assert run_cli(numproject, "verify").returncode == 0


def test_a_full_disk_is_said_plainly_and_the_next_run_recovers(numproject, monkeypatch, capsys):
    """ENOSPC while writing (here the run record, after the stages) ends the run with one line naming the file and
    what to do, exit 1 and no traceback; a run once there is room completes from what was stored."""
    import errno

    from msflow.cli import run_commands
    from msflow.stores.local import LocalStore

    def full(store, record):
        raise OSError(errno.ENOSPC, "No space left on device", str(store.root / "runs" / f"{record['id']}.json"))

    monkeypatch.chdir(numproject)
    with monkeypatch.context() as patched:
        patched.setattr(LocalStore, "write_run", full)
        code = run_commands(["run", "-q"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "error: cannot write (" in err and "runs" in err and "No space left on device" in err and "msflow gc" in err
    assert run_commands(["run", "-q"]) == 0
    assert msflow.run(numproject / "pipeline.yaml").executed == []
    assert not any((numproject / ".msflow" / "tmp").iterdir())


def test_a_failed_atomic_write_names_its_file_and_leaves_nothing(tmp_path):
    import errno

    from msflow.atomic import write_with

    def fail(fh):
        fh.write(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")  # as a full disk's write: no file name

    with pytest.raises(OSError) as raised:
        write_with(tmp_path / "out.bin", fail)
    assert raised.value.errno == errno.ENOSPC and raised.value.filename == str(tmp_path / "out.bin")
    assert list(tmp_path.iterdir()) == []
