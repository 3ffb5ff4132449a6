"""Remote (object) stores: the numeric project on S3 end to end, atomic publish, leases, cleanup and errors.

Every test talks to a moto S3 server on 127.0.0.1 that this module starts; credentials are dummies. Instance
metadata lookups are disabled (AWS_EC2_METADATA_DISABLED) so botocore never leaves the loopback.
"""

import json
import re
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from conftest import Hold, MotoS3, cli_env, damage_chunk, executions, run_cli, start_cli, wait_for_line

import msflow
from msflow.artifact import check_contents, encode_artifact, prepare_manifest
from msflow.errors import UserError
from msflow.stores import open_store
from msflow.stores.base import HOST
from msflow.stores.leases import Lease
from msflow.stores.remote import RemoteStore, open_remote_store, settle_releases

ROOT = Path(__file__).resolve().parents[1]


def on_s3(proj: Path, s3: MotoS3, bucket: str, files=("pipeline.yaml", "crash.yaml"), options=None, url=None) -> str:
    """Point the project's pipeline files at ``s3://bucket/num``; returns the store URL."""
    url = url or f"s3://{bucket}/num"
    header = f"store: {url}\nstore_options: {json.dumps(s3.options if options is None else options)}\n"
    for name in files:
        text = (proj / name).read_text()
        (proj / name).write_text(text.replace("version: 1\n", "version: 1\n" + header, 1))
    return url


async def together(event, seconds: float, label: str) -> str:
    """``label`` when ``event`` is set within ``seconds`` (two requests went out together), else "alone"."""
    import asyncio

    try:
        await asyncio.wait_for(event.wait(), seconds)
    except TimeoutError:
        return "alone"
    return label


def stage_keys(record: dict) -> dict:
    return {name: s["key"] for name, s in record["stages"].items()}


def uncommitted_folders(store: RemoteStore) -> set[str]:
    folders = {"/".join(o.path.split("/")[:4]) for o in store.objects.list("artifacts/")}
    committed = set()
    for key in store.keys():
        committed.add(store.data_path(key, json.loads(store.objects.get(store.marker_path(key)))["data"]))
    return folders - committed


def writes_of(store: RemoteStore, pid: int) -> set[str]:
    """Folders that process ``pid`` journalled for writing and has not finished (committed or abandoned)."""
    folders = set()
    for info in store.objects.list("pending/"):
        entry = json.loads(store.objects.get(info.path) or b"{}")
        if entry.get("action") == "write" and entry.get("pid") == pid:
            folders.add(store.data_path(entry["key"], entry["data"]))
    return folders


# ------------------------------------------------------------------------------------------- end to end
def test_numeric_project_on_s3_matches_a_local_store(numproject, tmp_path, s3):
    local = tmp_path / "local"
    import shutil

    shutil.copytree(numproject, local)
    bucket = s3.bucket()
    on_s3(numproject, s3, bucket)
    log = tmp_path / "log"
    env = {"NUMSTAGES_LOG": str(log)}

    first = run_cli(numproject, "run", "-q", env=env)
    assert first.returncode == 0, first.stderr
    assert sorted(executions(log)) == ["csv", "scaled", "sign", "src", "total"]
    assert not (numproject / ".msflow" / "artifacts").exists()  # artifacts went to S3, only the memo is local
    assert (numproject / ".msflow" / "cache" / "memo.json").is_file()

    noop = run_cli(numproject, "run", "-q", env=env)
    assert noop.returncode == 0 and len(executions(log)) == 5, noop.stderr

    changed = run_cli(numproject, "run", "-q", "-S", "scaled.factor=4", env=env)
    assert changed.returncode == 0, changed.stderr
    assert sorted(executions(log)[5:]) == ["scaled", "sign"]  # sign's output is unchanged: total stays cached

    # same keys and results as a local store
    assert run_cli(local, "run", "-q").returncode == 0
    store = s3.store(bucket, "num")
    runs = store.run_ids()
    assert len(runs) == 3
    local_record = json.loads(next((local / ".msflow" / "runs").glob("*.json")).read_text())
    assert stage_keys(store.read_run(runs[0])) == stage_keys(local_record)
    local_store = open_store(str(local / ".msflow"))
    for key in stage_keys(local_record).values():
        remote_view, local_view = store.open(key), local_store.open(key)
        assert remote_view.manifest["content_hash"] == local_view.manifest["content_hash"]
        for name in local_view.names:
            assert np.array_equal(remote_view[name], local_view[name])

    verify = run_cli(numproject, "verify")
    assert verify.returncode == 0 and "verified 7 artifacts: 0 corrupt" in verify.stdout, verify.stdout

    # the largest of the last run's artifacts: the rerun below makes it again, so the factor-3 versions stay
    # unreferenced (the largest of all depends on metadata lengths, and deleting one of those changed the count)
    corrupt_key = max(stage_keys(store.read_run(store.run_ids()[-1])).values(), key=store.size)
    damage_chunk(store, corrupt_key)
    found = run_cli(numproject, "verify")
    assert found.returncode == 1 and f"corrupt {corrupt_key}" in found.stdout and "1 corrupt" in found.stdout
    deleted = run_cli(numproject, "verify", "--delete")  # removed: dealt with, exit 0
    assert deleted.returncode == 0 and f"1 corrupt, removed ({corrupt_key[:12]})" in deleted.stdout, deleted.stdout
    assert run_cli(numproject, "run", "-q", "-S", "scaled.factor=4").returncode == 0
    assert run_cli(numproject, "verify").returncode == 0

    last_run = set(stage_keys(store.read_run(store.run_ids()[-1])).values())
    unreferenced = set(store.keys()) - last_run
    assert unreferenced  # at least the factor-3 versions of scaled and sign
    gc = run_cli(numproject, "gc", "--keep-runs", "1")
    removed = re.search(r"removed (\d+) artifacts? ", gc.stdout)
    assert gc.returncode == 0 and removed and int(removed.group(1)) == len(unreferenced), gc.stdout
    kept = set(store.keys())
    assert kept == last_run
    assert {k.split("/")[3] for k in s3.objects(bucket, "num/artifacts/")} == kept
    assert uncommitted_folders(store) == set()


def test_concurrent_runs_on_s3_execute_each_stage_once(numproject, tmp_path, s3):
    bucket = s3.bucket()
    on_s3(numproject, s3, bucket)
    log = tmp_path / "log"
    hold = Hold(tmp_path / "hold")
    env = {"NUMSTAGES_LOG": str(log), **hold.env}
    first = start_cli(numproject, "run", "crash.yaml", "-q", env=env)
    hold.wait_ready(first)  # the first run holds the lease of 'slow' and is inside the stage
    others = [start_cli(numproject, "run", "crash.yaml", "-q", env=env) for _ in range(2)]
    for proc in others:
        wait_for_line(proc, "stage 'slow' is being computed by another run")
    hold.release()
    outs = [p.communicate(timeout=120) for p in (first, *others)]
    assert [p.returncode for p in (first, *others)] == [0, 0, 0], outs
    assert sorted(executions(log)) == ["after", "scaled", "slow", "src"]
    store = s3.store(bucket, "num")
    records = [store.read_run(r) for r in store.run_ids()]
    assert len(records) == 3
    for stage in ("slow", "after", "src", "scaled"):
        assert sum(r["stages"][stage]["state"] == "ran" for r in records) == 1
    assert store.objects.list("locks/") == [] and store.objects.list("pending/") == []


def test_sigkilled_runs_leave_nothing_visible_and_the_next_run_recovers(numproject, tmp_path, s3):
    bucket = s3.bucket()
    on_s3(numproject, s3, bucket, files=("crash.yaml", "stream.yaml"))
    store = s3.store(bucket, "num")
    assert run_cli(numproject, "run", "crash.yaml", "-q").returncode == 0
    committed = {k: store.manifest(k) for k in store.keys()}
    # killed inside a forced stage (its lease held, nothing written), then mid-upload of a streamed output
    for pipeline, args in (("crash.yaml", ("--force", "slow")), ("stream.yaml", ("--until", "streamed"))):
        hold = Hold(tmp_path / pipeline)
        env = {**hold.env, "MSFLOW_STORE_PACK_MB": "0"}  # stream the chunks at once: killed mid-upload
        proc = start_cli(numproject, "run", pipeline, *args, "-q", env=env)
        hold.wait_ready(proc)
        written = writes_of(store, proc.pid)
        proc.kill()
        proc.wait()
        assert {k: store.manifest(k) for k in store.keys()} == committed  # nothing new visible, nothing replaced
        if pipeline == "stream.yaml":
            assert written and all(store.objects.list(f + "/") for f in written)  # chunks were uploaded
    result = run_cli(numproject, "run", "crash.yaml", "-q")
    assert result.returncode == 0, result.stderr
    assert run_cli(numproject, "run", "stream.yaml", "-q").returncode == 0
    verify = run_cli(numproject, "verify", "crash.yaml")
    assert verify.returncode == 0 and "0 corrupt" in verify.stdout, verify.stdout

    out = msflow.run(numproject / "crash.yaml")
    assert out.executed == []
    big = out.load("slow.big")
    assert np.array_equal(big, np.random.default_rng(7).standard_normal(3_000_000))
    assert out.load("after.total") == np.float64(big.sum() + 45)
    # killed writers' folders (dead pids on this host) and retired folders are gone after cleanup
    store.clean_tmp(max_age=0)
    assert uncommitted_folders(store) == set()
    assert store.objects.list("pending/") == [] and store.objects.list("locks/") == []


def test_gc_on_s3_refuses_while_a_run_on_any_machine_is_present(numproject, tmp_path, s3):
    """A run keeps a presence on the store (active/, renewed like a lease) while it runs, so gc, which keeps only
    what run records name, refuses instead of deleting what the run has made; the presence goes when the run
    ends, and a killed run's is stale at once on its own host (and after its ttl elsewhere)."""
    bucket = s3.bucket()
    on_s3(numproject, s3, bucket)
    store = s3.store(bucket, "num")
    hold = Hold(tmp_path / "hold")
    proc = start_cli(numproject, "run", "crash.yaml", "-q", env=hold.env)
    hold.wait_ready(proc)
    (present,) = store.objects.list("active/")
    status = run_cli(numproject, "status", "crash.yaml")  # the held stage's lease names its holder
    assert f"being computed now by a run in progress (pid {proc.pid} on " in status.stdout, status.stdout
    refused = run_cli(numproject, "gc", "crash.yaml")
    assert refused.returncode == 2 and "1 run(s) are using the store" in refused.stderr, refused.stderr
    assert f"pid {proc.pid} on " in refused.stderr and "Traceback" not in refused.stderr
    hold.release()
    assert proc.wait(timeout=120) == 0
    assert store.objects.list("active/") == []
    done = run_cli(numproject, "gc", "crash.yaml")
    assert done.returncode == 0 and "removed 0 artifacts" in done.stdout, (done.stdout, done.stderr)
    assert msflow.run(numproject / "crash.yaml").executed == []

    (hold.folder / "release").unlink()
    (hold.folder / "ready").unlink()
    killed = start_cli(numproject, "run", "crash.yaml", "--force", "slow", "-q", env=hold.env)
    hold.wait_ready(killed)
    killed.kill()
    killed.wait()
    assert len(store.objects.list("active/")) == 1  # left behind, but its holder is dead
    assert run_cli(numproject, "gc", "crash.yaml").returncode == 0
    assert store.objects.list("active/") == []


def test_a_run_on_s3_waits_for_a_gc_in_progress(numproject, s3):
    """gc is present on the store too (gc/) while it deletes, written before it lists the runs; a run that
    finds it after writing its own presence waits, saying so, and goes on once gc has ended. (Before, a run
    starting while gc deleted went ahead and could lose what it had just found cached.)"""
    from msflow.stores.leases import GC_PREFIX, Presence

    bucket = s3.bucket()
    on_s3(numproject, s3, bucket)
    store = s3.store(bucket, "num")
    with Presence(store.objects, prefix=GC_PREFIX):  # a gc deleting, here or on another machine
        proc = start_cli(numproject, "run", "-q")
        wait_for_line(proc, "msflow gc (pid ")
        assert list(store.keys()) == [] and proc.poll() is None  # it waits before it computes anything
        refused = run_cli(numproject, "gc")  # the waiting run is present: a second gc refuses
        assert refused.returncode == 2 and "1 run(s) are using the store" in refused.stderr, refused.stderr
    assert proc.wait(timeout=120) == 0, proc.stderr.read()
    assert len(list(store.keys())) == 5 and store.objects.list(GC_PREFIX) == []


def test_output_sinks_stream_to_s3_with_the_hashes_of_whole_arrays(numproject, s3):
    on_s3(numproject, s3, s3.bucket(), files=("stream.yaml",))
    out = msflow.run(numproject / "stream.yaml")
    assert out.states["streamed"].manifest["outputs"] == out.states["whole"].manifest["outputs"]
    frames = out.load("streamed.frames")
    assert frames.shape == (270_000, 16) and np.isclose(out.load("total.total"), frames.astype(np.float64).sum())
    store = out.session.store
    assert all(store.verify(key) == [] for key in store.keys())
    assert store.objects.list("pending/") == []


def test_a_corrupt_chunk_on_s3_is_caught_on_read_and_repaired(numproject, s3):
    bucket = s3.bucket()
    on_s3(numproject, s3, bucket)
    assert run_cli(numproject, "run", "-q").returncode == 0
    store = s3.store(bucket, "num")
    record = store.read_run(store.run_ids()[-1])
    key = record["stages"]["src"]["key"]
    damage_chunk(store, key, "x/c/0")
    shown = run_cli(numproject, "show", "src.x")
    assert shown.returncode == 1 and key in shown.stderr and "Traceback" not in shown.stderr, shown.stderr
    run = run_cli(numproject, "run", "-q", "-S", "scaled.factor=5")
    assert run.returncode == 0 and "was corrupt" in run.stderr, run.stderr
    assert [o.path for o in store.objects.list("corrupt/")] and store.verify(key) == []
    assert np.array_equal(msflow.run(numproject / "pipeline.yaml").load("src.x"), np.arange(6.0))
    # gc deletes what was set aside: the record in corrupt/ and the damaged data folder it names, nothing else
    folders = {o.path.split("/")[3] for o in store.objects.list(f"artifacts/{key[:2]}/{key}/")}
    assert len(folders) == 2  # the damaged one and the recomputed one
    gc = run_cli(numproject, "gc")
    assert gc.returncode == 0 and "removed 1 damaged artifact set aside" in gc.stdout, gc.stdout
    assert store.objects.list("corrupt/") == [] and store.verify(key) == []
    assert len({o.path.split("/")[3] for o in store.objects.list(f"artifacts/{key[:2]}/{key}/")}) == 1


def test_the_run_leaves_the_check_of_a_stage_whose_input_it_computed_to_the_worker(numproject, s3, monkeypatch):
    """Early cutoff on a remote store: src forced, its content unchanged. scaled's input was just computed, so
    the run does not ask the store for scaled (a round trip every executed stage would pay): the worker finds
    the artifact under scaled's lease, and it counts as a plain cache hit, not as a concurrent run's work.
    sign and total, whose inputs were cached, are checked by the run as before (no lease)."""
    on_s3(numproject, s3, s3.bucket())
    first = msflow.run(numproject / "pipeline.yaml")
    locked = []
    real_lock = RemoteStore.lock
    monkeypatch.setattr(RemoteStore, "lock", lambda self, key, **kw: locked.append(key) or real_lock(self, key, **kw))
    result = msflow.run(numproject / "pipeline.yaml", force=("src",))
    assert result.executed == ["src"]
    for name in ("scaled", "sign", "total", "csv"):
        state = result.states[name]
        assert state.state.value == "cached" and state.key == first.states[name].key, state
        assert state.detail == "", (name, state.detail)
    assert locked == [first.states["src"].key, first.states["scaled"].key]
    assert np.array_equal(result.load("total.total"), first.load("total.total"))


def test_a_damaged_artifact_found_by_the_worker_instead_of_the_run_is_moved_aside_and_recomputed(numproject, s3):
    """The worker's check (left to it by the run) meets scaled's unreadable commit marker: the run moves it
    aside and computes scaled again, as when the run's own check finds it."""
    bucket = s3.bucket()
    on_s3(numproject, s3, bucket)
    first = msflow.run(numproject / "pipeline.yaml")
    store = s3.store(bucket, "num")
    key = first.states["scaled"].key
    store.objects.put(store.marker_path(key), b"{not a marker")
    result = msflow.run(numproject / "pipeline.yaml", force=("src",))
    assert sorted(result.executed) == ["scaled", "src"]
    assert result.states["scaled"].detail == "recomputed: its artifact was corrupt"
    assert [r["stage"] for r in result.record["repairs"]] == ["scaled"], result.record.get("repairs")
    assert [o.path for o in store.objects.list("corrupt/")] and store.verify(key) == []
    assert np.array_equal(result.load("scaled.y"), first.load("scaled.y"))


# ------------------------------------------------------------------------------------------- store contract
@pytest.fixture(params=["s3", "memory"])
def any_store(request, s3):
    if request.param == "s3":
        return s3.store(s3.bucket())
    return open_store(f"memory://msflow-test/{uuid.uuid4().hex[:8]}", {})


def test_objects_say_which_exist_by_exact_path(any_store):
    objects = any_store.objects
    objects.put_many({"blobs/ab/abc": b"1", "blobs/ab/abcd": b"2", "blobs/cd/cde": b"3"})
    asked = ["blobs/ab/abc", "blobs/ab/ab", "blobs/cd/cde", "blobs/ef/nothing"]
    assert objects.exists_many(asked) == {
        "blobs/ab/abc": True,
        "blobs/ab/ab": False,  # a prefix of existing objects is no object
        "blobs/cd/cde": True,
        "blobs/ef/nothing": False,
    }
    assert objects.exists_many([]) == {}


def artifact_objects(arrays, meta):
    arrays, manifest = prepare_manifest(arrays, {"meta": meta, "metrics": {}})
    return dict(encode_artifact(arrays, manifest))


def test_store_contract_write_read_lazy_verify_remove(any_store):
    store = any_store
    rng = np.random.default_rng(0)
    arrays = {
        "big": rng.standard_normal((700_000, 2)),
        "scalar": np.array(3, dtype=np.int32),
        "empty": np.zeros((0, 4)),
        "flags": rng.random(17) > 0.5,
        "wave": rng.random(9).astype(">f4"),
    }
    key = "ab" + "0" * 30
    assert not store.has(key) and list(store.keys()) == []
    manifest = store.write(key, arrays, {"meta": {"note": "x"}, "metrics": {"m": 1.5}})
    assert store.has(key) and list(store.keys()) == [key]
    assert store.manifest(key) == manifest
    view = store.open(key)
    for name, arr in arrays.items():
        assert view[name].dtype == arr.dtype.newbyteorder("=") and np.array_equal(view[name], arr), name
    lazy = view.lazy("big")  # zarr semantics for partial reads
    assert lazy.shape == (700_000, 2) and lazy.chunks[0] < 700_000
    assert np.array_equal(lazy[123_456:400_000:7], arrays["big"][123_456:400_000:7])
    assert np.array_equal(lazy.oindex[[1, 5, 699_999], :], arrays["big"][[1, 5, 699_999]])
    assert view.meta == {"note": "x"} and view.metrics == {"m": 1.5}
    assert store.verify(key) == [] and store.size(key) > 1_000_000

    # a second writer of the key (no lock held) loses the commit: the first artifact stays, nothing is left over
    again = store.write(key, {"x": np.zeros(3)}, {"meta": {"note": "late"}})
    assert again == manifest and store.manifest(key) == manifest
    assert len({o.path.split("/")[3] for o in store.objects.list("artifacts/")}) == 1

    # a lost chunk object is found by verify
    chunk = next(o.path for o in store.objects.list("artifacts/") if o.path.endswith("big/c/1/0"))
    store.objects.delete(chunk)
    assert any("output 'big': unreadable" in p for p in store.verify(key))
    store.remove(key)
    assert not store.has(key) and list(store.keys()) == [] and store.objects.list("artifacts/") == []


def test_uncommitted_objects_are_invisible_and_cleaned_by_age_or_dead_writer(s3):
    store = s3.store(s3.bucket())
    done = "cd" + "1" * 30
    store.write(done, {"x": np.arange(5.0)}, {})
    dead_pid = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    writers = {
        "ee" + "2" * 30: {"host": HOST, "pid": int(dead_pid)},  # killed on this host
        "ef" + "3" * 30: {"host": "elsewhere", "pid": 1},  # another host, no lease
        "f0" + "4" * 30: {"host": "elsewhere", "pid": 1},
    }  # another host, live lease
    for key, writer in writers.items():
        wid = f"0-{key[:4]}"
        store.objects.put(
            store.journal_path(key, wid),
            json.dumps({"key": key, "data": wid, "action": "write", "started": time.time(), **writer}).encode(),
        )
        store.objects.put_many(
            {
                f"{store.data_path(key, wid)}/{rel}": data
                for rel, data in artifact_objects({"x": np.ones(3)}, {}).items()
            }
        )
    live = "f0" + "4" * 30
    store.objects.put(
        store.lease_path(live),
        json.dumps({"owner": "o", "host": "elsewhere", "pid": 1, "ttl": 60, "renewed": time.time()}).encode(),
    )
    for key in writers:
        assert not store.has(key)
        with pytest.raises(FileNotFoundError):
            store.open(key)
        assert store.verify(key) == ["no commit marker (not published)"]
    assert list(store.keys()) == [done]

    assert store.clean_tmp() == [f"{'ee' + '2' * 30}.0-ee22"]  # dead local pid: at once
    assert store.clean_tmp(max_age=0) == [f"{'ef' + '3' * 30}.0-ef33"]  # old enough, no lease
    assert store.clean_tmp(max_age=0) == []  # a live lease keeps its writer's folder
    assert uncommitted_folders(store) == {store.data_path(live, "0-f044")}
    assert store.has(done) and store.verify(done) == []


def test_replace_swaps_whole_artifacts_under_concurrent_readers(s3):
    store = s3.store(s3.bucket())
    key = "aa" + "5" * 30
    versions = [{"x": np.full(50_000, float(i)), "y": np.arange(i + 3)} for i in range(2)]
    store.write(key, versions[0], {"meta": {"v": 0}})
    seen, problems, stop = set(), [], threading.Event()
    reads = [0]
    progress = threading.Condition()

    def reader():
        reader_store = RemoteStore(store.url, store.options)
        while not stop.is_set():
            view = reader_store.open(key)
            found = check_contents(view.manifest, view.__getitem__)
            problems.extend(found)
            seen.add(float(view["x"][0]))
            if view["y"].shape != (int(view["x"][0]) + 3,):
                problems.append("mixed versions")
            with progress:
                reads[0] += 1
                progress.notify_all()

    thread = threading.Thread(target=reader)
    thread.start()
    for i in range(1, 9):
        store.write(key, versions[i % 2], {"meta": {"v": i % 2}}, replace=True)
        with progress:  # a whole read that began after this write (handshake, not a guessed delay)
            target = reads[0] + 2
            assert progress.wait_for(lambda: reads[0] >= target or not thread.is_alive(), timeout=120)
    stop.set()
    thread.join()
    assert problems == [] and seen == {0.0, 1.0}
    assert len(store.objects.list("pending/")) == 8  # eight retired folders, readable for a grace period
    assert len(store.clean_tmp(max_age=0)) == 8
    assert uncommitted_folders(store) == set() and store.verify(key) == []


# ------------------------------------------------------------------------------------------- leases
def start_contenders(store, key: str, threads: int, rounds: int) -> tuple[list[threading.Thread], list[int]]:
    """Threads that each take ``key``'s lock ``rounds`` times, started; the list gets, at each entry, how many
    threads were inside (1 while the lock excludes)."""
    inside, overlaps = [0], []

    def contender():
        for _ in range(rounds):
            with store.lock(key):
                inside[0] += 1
                overlaps.append(inside[0])
                time.sleep(0.02)
                inside[0] -= 1

    started = [threading.Thread(target=contender) for _ in range(threads)]
    for t in started:
        t.start()
    return started, overlaps


def test_leases_exclude_each_other_renew_and_break_when_stale(s3):
    store = s3.store(s3.bucket())
    # mutual exclusion among racing threads
    threads, overlaps = start_contenders(store, "k-excl", threads=4, rounds=3)

    # a lease held with a short ttl stays valid through heartbeats ...
    holder = Lease(store.objects, store.lease_path("k-beat"), ttl=1.0)
    holder.acquire()
    waiter_result = []

    def waiter():
        try:
            Lease(store.objects, store.lease_path("k-beat")).acquire(timeout=6.0)
            waiter_result.append("acquired")
        except TimeoutError:
            waiter_result.append("timeout")

    beat = threading.Thread(target=waiter)
    beat.start()

    # ... while one whose holder stopped renewing is broken once older than its ttl (server clock)
    store.objects.put(
        store.lease_path("k-expired"),
        json.dumps({"owner": "gone", "host": "elsewhere", "pid": 1, "ttl": 1, "renewed": time.time()}).encode(),
    )
    waits = []
    expired = Lease(store.objects, store.lease_path("k-expired"))
    expired.acquire(on_wait=waits.append, timeout=60)  # waited (not broken at once), then broke it
    expired.release()
    assert waits and waits[0]["host"] == "elsewhere"

    # a dead holder on this host is broken at once, a live one elsewhere is waited for
    dead = int(
        subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout
    )
    store.objects.put(
        store.lease_path("k-dead"),
        json.dumps({"owner": "gone", "host": HOST, "pid": dead, "ttl": 60, "renewed": time.time()}).encode(),
    )
    waits = []
    with store.lock("k-dead", on_wait=waits.append):
        assert waits == []  # broken at once: no waiting
    store.objects.put(
        store.lease_path("k-live"),
        json.dumps({"owner": "busy", "host": "elsewhere", "pid": 1, "ttl": 60, "renewed": time.time()}).encode(),
    )
    with pytest.raises(TimeoutError):
        Lease(store.objects, store.lease_path("k-live")).acquire(timeout=0.5)

    beat.join()
    assert waiter_result == ["timeout"] and not holder.lost
    holder.release()
    with store.lock("k-beat"):
        pass
    for t in threads:
        t.join()
    assert len(overlaps) == 12 and max(overlaps) == 1


def test_a_lease_trusts_its_create_only_where_the_server_honours_if_none_match(s3, monkeypatch):
    from msflow.stores import objects as objects_module

    monkeypatch.setattr(objects_module, "_EXCLUSIVE_CREATE", {})
    store = s3.store(s3.bucket())
    calls = []
    real_call = objects_module.S3Objects._call

    async def counted(self, method, **kwargs):
        calls.append((method, kwargs.get("Key", "")))
        return await real_call(self, method, **kwargs)

    async def failing(self, method, **kwargs):
        if ".create-probe-" in kwargs.get("Key", "") and method == "put_object":
            raise ConnectionResetError("network blip")
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module.S3Objects, "_call", failing)
    assert not store.objects.creates_exclusively()  # no answer: the safe path, and not remembered
    assert objects_module._EXCLUSIVE_CREATE == {}
    monkeypatch.setattr(objects_module.S3Objects, "_call", counted)
    assert store.objects.creates_exclusively()  # moto refuses a second create
    assert store.objects.list("locks/") == []  # the probe object is gone
    calls.clear()
    with store.lock("k-trusted") as lease:
        assert calls == [("put_object", store.objects._key(store.lease_path("k-trusted")))]  # no read-back
        assert lease.etag == store.objects.get_versioned(store.lease_path("k-trusted")).etag

    # a server that ignores the condition: the probe says so, and the read-back keeps the leases exclusive
    async def ignoring(self, method, **kwargs):
        kwargs.pop("IfNoneMatch", None)
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module, "_EXCLUSIVE_CREATE", {})
    monkeypatch.setattr(objects_module.S3Objects, "_call", ignoring)
    assert not store.objects.creates_exclusively()
    threads, overlaps = start_contenders(store, "k-ignored", threads=3, rounds=2)
    for t in threads:
        t.join()
    assert len(overlaps) == 6 and max(overlaps) == 1


def test_the_journal_is_deleted_together_with_the_lease_release(s3, monkeypatch):
    """After a commit under a lease, the journal's delete and the lease's delete go out together (one round trip):
    the journal's delete waits, on the store's event loop, until the lease's delete has started."""
    import asyncio

    from msflow.stores import objects as objects_module

    store = s3.store(s3.bucket())
    real_call = objects_module.S3Objects._call
    lease_deleting = asyncio.Event()
    journal_deletes = []

    async def paired(self, method, **kwargs):
        path = kwargs.get("Key", "")
        if method == "delete_object" and path.endswith(".lease"):
            lease_deleting.set()
        elif method == "delete_object" and "/pending/" in f"/{path}":
            journal_deletes.append(await together(lease_deleting, 5, "with the lease's"))
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module.S3Objects, "_call", paired)
    key = "cd" + "1" * 30
    with store.lock(key):
        store.write(key, {"x": np.arange(5)}, {"meta": {}, "metrics": {}})
    settle_releases()
    assert journal_deletes == ["with the lease's"]
    assert store.objects.list("pending/") == [] and store.objects.list("locks/") == []
    assert np.array_equal(store.open(key)["x"], np.arange(5))


def test_a_stage_journals_its_folder_while_the_lease_holder_checks_for_a_published_artifact(
    numproject, s3, monkeypatch
):
    """Under the lease, the journal's PUT and the re-check for an artifact published meanwhile go out together
    (one round trip): the re-check's GET waits, on the store's event loop, until the journal's PUT has started."""
    import asyncio

    from msflow.stores import objects as objects_module

    bucket = s3.bucket()
    on_s3(numproject, s3, bucket, files=("pipeline.yaml",))
    real_call = objects_module.S3Objects._call
    leased: set[str] = set()
    journalling: dict[str, asyncio.Event] = {}
    journals = []

    async def paired(self, method, **kwargs):
        path = kwargs.get("Key", "")
        key = path.rsplit("/", 1)[-1].split(".")[0]
        event = journalling.setdefault(key, asyncio.Event())
        if method == "put_object" and path.endswith(".lease"):
            leased.add(key)
        elif method == "put_object" and "/pending/" in f"/{path}":
            event.set()
        elif method == "get_object" and "/commits/" in f"/{path}" and key in leased:
            leased.discard(key)  # the first read under the lease is the re-check
            journals.append(await together(event, 2, "with the re-check"))
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module.S3Objects, "_call", paired)
    result = msflow.run(numproject / "pipeline.yaml")
    assert len(result.executed) == 5 and journals == ["with the re-check"] * 5
    store = s3.store(bucket, "num")
    assert store.objects.list("pending/") == [] and store.objects.list("locks/") == []
    assert uncommitted_folders(store) == set()


def test_a_writer_that_finds_the_artifact_published_meanwhile_takes_back_only_its_journal(s3, monkeypatch):
    """The re-check under the lease finds the key committed: the writer made for it uploaded nothing, so it
    deletes its journal entry and nothing else (no marker read, no listing of its folder)."""
    from msflow.stores import objects as objects_module

    store = s3.store(s3.bucket())
    key = "ef" + "2" * 30
    store.write(key, {"x": np.arange(3)}, {"meta": {}, "metrics": {}})
    real_call = objects_module.S3Objects._call
    calls = []

    async def logged(self, method, **kwargs):
        calls.append((method, kwargs.get("Key", kwargs.get("Prefix", "")).split("/")[1]))
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module.S3Objects, "_call", logged)
    with store.lock(key), store.writer(key):
        assert store.has(key)
    settle_releases()
    assert sorted(calls) == sorted(
        [
            ("put_object", "locks"),
            ("put_object", "pending"),
            ("get_object", "commits"),  # the re-check
            ("delete_object", "pending"),
            ("delete_object", "locks"),
        ]
    )
    assert store.objects.list("pending/") == [] and store.objects.list("locks/") == []
    assert {o.path.split("/")[3] for o in store.objects.list("artifacts/")} == {store._marker(key)["data"]}


def test_a_stage_reads_the_input_its_process_just_committed_without_asking_the_store(numproject, s3, monkeypatch):
    """In one process, a stage whose input was committed a moment ago reads it from memory: only the checks GET
    anything, the one under each stage's lease, and the run's own of the two stages (src, csv) whose inputs were
    not computed by the run (Runner.needs_check). With the cache off
    (MSFLOW_STORE_CACHE_MB=0) the input's marker and chunks are fetched, and the results are the same."""
    from msflow.stores import objects as objects_module

    real_call = objects_module.S3Objects._call
    gets = []

    async def logged(self, method, **kwargs):
        if method == "get_object":
            gets.append(kwargs["Key"].split("/")[1])
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module.S3Objects, "_call", logged)
    loads = {}
    for megabytes in ("64", "0"):
        monkeypatch.setenv("MSFLOW_STORE_CACHE_MB", megabytes)
        bucket = s3.bucket()  # a fresh store URL: its caches are made with this capacity
        (numproject / "pipeline.yaml").write_text((ROOT / "tests/numproject/pipeline.yaml").read_text())
        on_s3(numproject, s3, bucket, files=("pipeline.yaml",))
        gets.clear()
        result = msflow.run(numproject / "pipeline.yaml")
        assert len(result.executed) == 5
        loads[megabytes] = {name: result.load(f"{name}.{output}") for name, output in (("scaled", "y"), ("src", "x"))}
        if megabytes == "64":
            assert gets.count("commits") == 5 + 2 and "artifacts" not in gets, gets
        else:
            assert "artifacts" in gets and gets.count("commits") > 5 + 2, gets
    for name in loads["64"]:
        assert np.array_equal(loads["64"][name], loads["0"][name])


def test_verify_reads_the_store_not_what_the_process_remembers(s3):
    """A chunk damaged on the server after this process wrote it: reading in this process returns the data it
    wrote (the cache holds exactly what was uploaded), and verify, which always reads the server, reports it."""
    store = s3.store(s3.bucket())
    key = "ab" + "3" * 30
    store.write(key, {"x": np.arange(4.0)}, {"meta": {}, "metrics": {}})
    damage_chunk(store, key, "x/c/0")
    assert np.array_equal(store.open(key)["x"], np.arange(4.0))
    problems = store.verify(key)
    assert problems and "x" in " ".join(problems), problems


def test_recent_objects_stay_within_their_capacity_and_markers_expire(monkeypatch):
    from msflow.stores import recent

    objects = recent.RecentObjects(capacity=800)
    for i in range(10):
        objects.put(f"o{i}", bytes(90))
    objects.get("o3")  # used: kept over older ones
    objects.put("o10", bytes(90))
    kept = [f"o{i}" for i in range(11) if objects.get(f"o{i}") is not None]
    assert objects.size <= 800 and "o3" in kept and "o10" in kept and "o0" not in kept
    objects.put("big", bytes(101))  # over an eighth of the capacity: not kept
    assert objects.get("big") is None

    now = [1000.0]
    monkeypatch.setattr(recent.time, "monotonic", lambda: now[0])
    markers = recent.RecentMarkers(max_age=15.0)
    markers.put("k", {"data": "w1"})
    now[0] += 14.0
    assert markers.get("k") == {"data": "w1"}
    now[0] += 2.0
    assert markers.get("k") is None


def test_a_lease_is_released_without_waiting_and_settled_before_the_run_ends(numproject, s3, monkeypatch):
    """The lease's release is sent when the locked block ends and not waited for: the block returns while the
    DELETE is still held back here. Locking the key again waits for that release, settle_releases waits for all,
    and a run (inline, a process pool) ends with no lease left in the store."""
    import asyncio

    from msflow.stores import objects as objects_module

    store = s3.store(s3.bucket())
    real_call = objects_module.S3Objects._call
    let_go = threading.Event()

    async def held_back(self, method, **kwargs):
        if method == "delete_object" and kwargs.get("Key", "").endswith(".lease"):
            await asyncio.get_running_loop().run_in_executor(None, let_go.wait, 10)
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module.S3Objects, "_call", held_back)
    key = "aa" + "4" * 30
    with store.lock(key):
        pass
    assert [o.path for o in store.objects.list("locks/")] == [f"locks/{key}.lease"]  # released in the background
    threading.Timer(0.3, let_go.set).start()
    with store.lock(key):  # waits for our own release first, then takes the key at once
        pass
    settle_releases()
    assert store.objects.list("locks/") == []
    monkeypatch.undo()

    bucket = s3.bucket()
    on_s3(numproject, s3, bucket, files=("pipeline.yaml",))
    for jobs in ("1", "2"):
        run = run_cli(numproject, "run", "-q", "-j", jobs, "-S", f"scaled.factor={jobs}")
        assert run.returncode == 0, run.stderr
        assert s3.store(bucket, "num").objects.list("locks/") == [], jobs


# ------------------------------------------------------------------------------------------- errors
def cli_without_aws_env(proj, *args, extra=None, timeout=60):
    env = {k: v for k, v in cli_env().items() if not k.startswith("AWS_")}
    env.update(
        {
            "AWS_EC2_METADATA_DISABLED": "true",
            "AWS_SHARED_CREDENTIALS_FILE": "/nonexistent",
            "AWS_CONFIG_FILE": "/nonexistent",
        },
        **(extra or {}),
    )
    return subprocess.run(
        [sys.executable, "-m", "msflow.cli", *args], cwd=proj, env=env, capture_output=True, text=True, timeout=timeout
    )


def test_store_errors_are_user_errors_naming_the_store(numproject, s3):
    pipeline = numproject / "pipeline.yaml"
    original = pipeline.read_text()

    def attempt(url, options, extra=None, timeout=60):  # timeout: a guard against hanging, not a speed test
        pipeline.write_text(original)
        on_s3(numproject, s3, "", files=("pipeline.yaml",), options=options, url=url)
        result = cli_without_aws_env(numproject, "run", "-q", extra=extra, timeout=timeout)
        assert result.returncode == 2, (url, result.stdout, result.stderr)
        assert url in result.stderr and "Traceback" not in result.stderr, result.stderr
        return result.stderr

    message = attempt("gs://bucket/prefix", {})
    assert "gcsfs" in message
    message = attempt("nosuchscheme://bucket/prefix", {})
    assert "unknown URL scheme" in message
    message = attempt(f"s3://{s3.bucket()}/p", {"endpoint_url": s3.endpoint})
    assert "no credentials" in message and "AWS_ACCESS_KEY_ID" in message
    message = attempt("s3://no-such-bucket/p", s3.options)
    assert "does not exist" in message
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    message = attempt(f"s3://{s3.bucket()}/p", dict(s3.options, endpoint_url=f"http://127.0.0.1:{port}"), timeout=30)
    assert "cannot reach" in message
    with socket.socket() as silent:  # accepts connections, never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        url = f"http://127.0.0.1:{silent.getsockname()[1]}"
        message = attempt(
            f"s3://{s3.bucket()}/p",
            dict(s3.options, endpoint_url=url),
            extra={"MSFLOW_STORE_TIMEOUT": "1.5"},
            timeout=10,
        )
    assert "cannot reach" in message
    assert not (numproject / ".msflow" / "runs").exists()


def test_open_remote_store_rejects_bad_options_and_urls(s3):
    with pytest.raises(UserError, match="invalid store_options"):
        open_remote_store(f"s3://{s3.bucket()}/p", {"no_such_option": 1})
    with pytest.raises(UserError, match="no bucket"):
        open_remote_store("s3://", s3.options)


def test_a_small_artifact_is_one_object_that_zarr_opens_and_a_large_one_stays_loose(s3, tmp_path, monkeypatch):
    """Eleven small outputs go up as one PUT (msflow.stores.packs), read back exactly, lazily through zarr too,
    and the downloaded pack is a zarr v3 group with the manifest; over the limit the objects stay loose."""
    import zarr

    from msflow.stores import objects as objects_module
    from msflow.stores import packs

    puts = []
    real_call = objects_module.S3Objects._call

    async def logged(self, method, **kwargs):
        if method == "put_object" and kwargs["Key"].split("/")[1] == "artifacts":
            puts.append(kwargs["Key"])
        return await real_call(self, method, **kwargs)

    monkeypatch.setattr(objects_module.S3Objects, "_call", logged)
    store = s3.store(s3.bucket())
    arrays = {f"a{i}": np.arange(i * 10.0).reshape(i, 10) for i in range(10)} | {"s": np.array(7, np.int16)}
    key = "ab" + "4" * 30
    manifest = store.write(key, arrays, {"meta": {"note": "small"}})
    assert len(puts) == 1 and puts[0].endswith(f"/{packs.PACK_NAME}") and store._marker(key)["pack"] == packs.PACK_NAME
    for cached in (True, False):  # from this process's recent objects, then from the server
        view = store._view(key, store._marker(key), cached=cached)
        assert all(np.array_equal(view[name], arr) for name, arr in arrays.items())
        assert np.array_equal(view.lazy("a9").oindex[[0, 8], 3:5], arrays["a9"][[0, 8], 3:5])  # through zarr
    assert store.verify(key) == []
    downloaded = tmp_path / "artifact.zip"
    downloaded.write_bytes(store.objects.get(puts[0].split("/", 1)[1]))
    group = zarr.open_group(zarr.storage.ZipStore(downloaded, mode="r"), mode="r")
    assert group.attrs["msflow"] == manifest and np.array_equal(group["a7"][...], arrays["a7"])

    monkeypatch.setenv("MSFLOW_STORE_PACK_MB", "0.001")  # 1000 bytes
    puts.clear()
    store.write("cd" + "4" * 30, arrays, {})
    assert len(puts) == 2 * len(arrays) - 1 + 1 and not any(p.endswith(packs.PACK_NAME) for p in puts)  # a0 is empty
    assert not store._marker("cd" + "4" * 30).get("pack") and store.verify("cd" + "4" * 30) == []


def test_a_damaged_pack_is_a_corrupt_artifact(s3):
    from msflow.errors import CorruptArtifact
    from msflow.stores.packs import PACK_NAME

    store = s3.store(s3.bucket())
    key = "ab" + "5" * 30
    store.write(key, {"x": np.arange(6.0), "y": np.ones(3)}, {})
    path = f"{store.data_path(key, store._marker(key)['data'])}/{PACK_NAME}"
    store.objects.put(path, store.objects.get(path)[:-40])  # cut short: no central directory
    with pytest.raises(CorruptArtifact, match="not a readable zip"):
        store._view(key, store._marker(key), cached=False)["x"]
    assert any("not a readable zip" in p for p in store.verify(key))
    other = "ab" + "6" * 30
    store.write(other, {"z": np.arange(9.0)}, {})
    damage_chunk(store, other, "z/c/0")  # a pack whose zip is sound, with a damaged chunk in it
    with pytest.raises(CorruptArtifact, match="checksum"):
        store._view(other, store._marker(other), cached=False)["z"]


def test_an_output_sinks_chunks_wait_for_the_pack_while_small_and_stream_beyond_it(s3, monkeypatch):
    """A sink's chunks are held for the pack up to the limit (the default pipeline's tracking stages: 29-35
    objects each otherwise); past it the held ones go up and the rest stream, so memory stays bounded."""
    from msflow.sinks import OutputSink
    from msflow.stores.packs import PACK_NAME

    store = s3.store(s3.bucket())
    rows = np.arange(3000 * 4, dtype=np.float32).reshape(3000, 4)
    for megabytes, packed in (("8", True), ("0.01", False)):
        monkeypatch.setenv("MSFLOW_STORE_PACK_MB", megabytes)
        key = ("ab" if packed else "cd") + "7" * 30
        with store.writer(key) as writer:
            sink = OutputSink("frames", "float32", (4,), target=writer)
            for block in np.split(rows, 6):
                sink.append(block)
            writer.commit({"frames": sink, "n": np.array(3000)}, {})
        folder = store.data_path(key, store._marker(key)["data"])
        names = {o.path[len(folder) + 1 :] for o in store.objects.list(folder + "/")}
        assert (names == {PACK_NAME}) == packed and bool(store._marker(key).get("pack")) == packed, names
        view = store._view(key, store._marker(key), cached=False)
        assert np.array_equal(view["frames"], rows) and store.verify(key) == []


def test_parts_on_s3_are_reused_verified_and_kept_by_gc(numproject, tmp_path, s3, monkeypatch):
    log = tmp_path / "exec.log"
    monkeypatch.setenv("NUMSTAGES_LOG", str(log))
    bucket = s3.bucket()
    on_s3(numproject, s3, bucket, files=("parts.yaml",))
    (numproject / "takes").mkdir()
    for name, values in {"a": "1\n2\n", "b": "3\n"}.items():
        (numproject / "takes" / f"{name}.txt").write_text(values)
    first = msflow.run(numproject / "parts.yaml")
    store = s3.store(bucket, "num")
    part_a = first.states["per_take"].manifest["parts"]["keys"]["a.txt"]
    damage_chunk(store, part_a)
    (numproject / "takes" / "c.txt").write_text("4\n")
    log.unlink()
    second = msflow.run(numproject / "parts.yaml")
    parts = second.states["per_take"].manifest["parts"]
    assert parts["reused"] == ["b.txt"]  # a's part was damaged: set aside and computed again
    assert sorted(line.split()[1] for line in log.read_text().splitlines() if line.startswith("part ")) == [
        "a.txt",
        "c.txt",
    ]
    np.testing.assert_array_equal(second.load("per_take.values"), [1, 2, 3, 4])
    from msflow.gc import collect_garbage

    collect_garbage(store, keep_runs=1)
    assert all(store.has(key) for key in parts["keys"].values())
