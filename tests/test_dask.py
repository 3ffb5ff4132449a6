"""The Dask executor: same keys and results as local runs, lost workers retried, clean errors, and a stand-in for
another machine.

The stand-in (``cluster`` fixture, one per module): a ``dask scheduler`` and two ``dask worker`` processes started
in their own working directory, in a separate mount namespace where the project copies, this checkout and every
source folder on ``sys.path`` are covered by empty tmpfs mounts, and (as root) as the user ``nobody``. Their
Python environment is the interpreter's own plus a copy of the ``msflow`` package; the store is S3 served by moto
on loopback. So whatever runs there reaches the workers through the store or the job, as on another machine.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, Hold, copy_project, executions, missing_tool, run_cli, start_cli
from test_remote_store import on_s3, uncommitted_folders

import msflow
from msflow.dask_executor import parse_scheduler_address
from msflow.errors import UserError
from msflow.stores import open_store

NOBODY = 65534
#: what the README's worker recipe pre-imports for the default pipeline's stages (msflow.dask_setup)
WORKER_IMPORTS = "scipy.signal,scipy.ndimage,scipy.optimize,scipy.spatial.transform,cv2,av,parselmouth,pygltflib"


# ------------------------------------------------------------------------------------------------ LocalCluster
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
        stage = remote.record["stages"][name]
        assert stage["worker"].startswith("tcp://127.0.0.1:") and stage["attempts"] == 1
    assert str(os.getpid()) not in {line.split()[1] for line in log.read_text().splitlines()}


def test_worker_killed_mid_stage_is_retried_without_partial_artifacts(numproject, tmp_path, monkeypatch):
    marker = tmp_path / "attempted"
    log = tmp_path / "log"
    monkeypatch.setenv("NUMSTAGES_MARKER", str(marker))
    monkeypatch.setenv("NUMSTAGES_LOG", str(log))
    result = msflow.run(numproject / "dieonce.yaml", executor="dask", jobs=1)
    assert marker.exists()  # the first attempt died
    assert result.states["die"].state == "ran" and executions(log).count("die") == 1
    assert result.record["stages"]["die"]["attempts"] == 2 and result.record["stages"]["src"]["attempts"] == 1
    assert np.allclose(result.load("die.y"), np.arange(5.0) + 1)
    assert run_cli(numproject, "verify", "dieonce.yaml").returncode == 0
    tmp = numproject / ".msflow" / "tmp"
    assert not tmp.exists() or not any(tmp.iterdir())


def test_a_local_cluster_leaves_nothing_in_the_temporary_folder(numproject, tmp_path):
    """Dask's workers keep their scratch space in $TMPDIR/dask-scratch-space by default, and its lock files
    stay after the cluster closes; msflow gives them a folder of their own and deletes it."""
    scratch = tmp_path / "tmpdir"
    scratch.mkdir()
    run = run_cli(numproject, "run", "-q", "--executor", "dask", "-j", "2", env={"TMPDIR": str(scratch)})
    assert run.returncode == 0, run.stderr
    assert sorted(p.relative_to(scratch).as_posix() for p in scratch.rglob("*")) == []


def test_sweep_on_dask_matches_local(numproject, tmp_path):
    from msflow.sweep import expand_variants, run_sweep

    variants = expand_variants(["src.n=3,4"], None)
    local = run_sweep(numproject / "pipeline.yaml", variants)
    clone = tmp_path / "dask"
    shutil.copytree(numproject, clone, ignore=shutil.ignore_patterns(".msflow"))
    remote = run_sweep(clone / "pipeline.yaml", variants, executor="dask", jobs=2)
    assert [v.metrics for v in remote.variants] == [v.metrics for v in local.variants]
    assert remote.executed == local.executed


def test_local_cluster_workers_run_without_the_malloc_trim_default():
    from msflow.dask_executor import DaskExecutor

    executor = DaskExecutor(jobs=1)
    try:
        found = executor.client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_")
    finally:
        executor.shutdown()
    assert list(found.values()) == [None]


def scheduler_transitions(dask_scheduler):
    """(key, from, to) of every task transition the scheduler made, in order."""
    return [(str(entry[0]), entry[1], entry[2]) for entry in dask_scheduler.transition_log]


def test_a_stage_reaches_the_scheduler_before_the_previous_result_is_released(numproject, monkeypatch):
    """Dask batches a client's messages (10 ms) and the scheduler's to a worker (5 ms): a submission sent right
    after a release waited for the release's batch. The executor sends at once and releases a result only after
    the next submission, so in a chain each stage is submitted before its input's task is released."""
    from msflow import dask_executor

    seen = {}
    shutdown = dask_executor.DaskExecutor.shutdown

    def record_then_shut_down(self, **kwargs):
        seen["interval"] = self.client.scheduler_comm.interval
        seen["log"] = self.client.run_on_scheduler(scheduler_transitions)
        shutdown(self, **kwargs)

    monkeypatch.setattr(dask_executor.DaskExecutor, "shutdown", record_then_shut_down)
    msflow.run(numproject / "pipeline.yaml", executor="dask", jobs=1)
    assert seen["interval"] == 0.0
    log = seen["log"]

    def first(stage, start, finish):
        found = [
            i for i, (key, a, b) in enumerate(log) if key.startswith(f"msflow-{stage}-") and (a, b) == (start, finish)
        ]
        assert found, (stage, start, finish, [entry for entry in log if stage in entry[0]])
        return found[0]

    for upstream, stage in (("src", "scaled"), ("scaled", "sign")):
        assert first(stage, "released", "waiting") < first(upstream, "memory", "forgotten"), (upstream, stage)


# ------------------------------------------------------------------------------------------------ addresses
@pytest.mark.parametrize(
    "address, cause",
    [
        ("tcp://127.0.0.1:notaport", "the port 'notaport' is not a number"),
        ("http://127.0.0.1:8787", "unknown scheme 'http://' (http:// is the dashboard's address)"),
        ("tcp://", "expected tcp://HOST:PORT"),
        ("", "expected tcp://HOST:PORT"),
        ("tcp://127.0.0.1:99999", "the port 99999 is out of range"),
        ("tcp://host:8786/path", "expected tcp://HOST:PORT"),
    ],
)
def test_malformed_scheduler_addresses_are_named_with_their_fault(address, cause):
    with pytest.raises(UserError) as info:
        parse_scheduler_address(address)
    assert f"invalid Dask scheduler address '{address}': {cause}" in str(info.value)
    assert info.value.field == "--scheduler"


def test_scheduler_addresses_default_to_tcp_and_port_8786():
    assert parse_scheduler_address("10.0.0.5").url == "tcp://10.0.0.5:8786"
    assert parse_scheduler_address("tcp://[::1]:9000").url == "tcp://[::1]:9000"
    assert parse_scheduler_address(" tls://sched.example:8786 ").url == "tls://sched.example:8786"


def test_an_unknown_scheduler_host_is_named():
    from msflow.dask_executor import probe

    with pytest.raises(UserError) as info:
        probe(parse_scheduler_address("tcp://no-such-host.invalid:8786"), 5)
    assert "cannot reach the Dask scheduler at tcp://no-such-host.invalid:8786: unknown host" in str(info.value)


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:notaport", ""])  # "": an unset $SCHEDULER, not a local run
def test_malformed_scheduler_address_fails_before_any_stage_runs(numproject, tmp_path, address):
    log = tmp_path / "log"
    result = run_cli(numproject, "run", "--scheduler", address, env={"NUMSTAGES_LOG": str(log)})
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"invalid Dask scheduler address '{address}'" in result.stderr
    assert executions(log) == []


def test_unreachable_scheduler_is_a_clear_error_for_run_and_sweep(numproject):
    import socket

    with socket.socket() as sock:  # a port nothing listens on: bound, never listening
        sock.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{sock.getsockname()[1]}"
        run = run_cli(numproject, "run", "--scheduler", address, "--connect-timeout", "1.5", "--force", "src")
        sweep = run_cli(numproject, "sweep", "-S", "src.n=3,4", "--scheduler", address, "--connect-timeout", "1.5")
    for result in (run, sweep):
        assert result.returncode == 2, result.stderr
        assert f"cannot reach the Dask scheduler at {address}: connection refused" in result.stderr
        assert "Traceback" not in result.stderr


def test_a_port_that_is_no_scheduler_is_a_clear_error(numproject):
    import socket

    with socket.socket() as sock:  # accepts TCP connections (backlog) but never speaks Dask
        sock.bind(("127.0.0.1", 0))
        sock.listen(8)
        address = f"127.0.0.1:{sock.getsockname()[1]}"
        result = run_cli(numproject, "run", "--scheduler", address, "--connect-timeout", "2", "--force", "src")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"cannot reach the Dask scheduler at {address}: the port answers, but no Dask handshake within 2s" in (
        result.stderr
    )


def test_a_port_that_speaks_another_protocol_is_a_clear_error(numproject):
    """A server that answers in its own protocol (here an HTTP proxy's 400, as one on this machine does for
    unrouted addresses): its reply read as Dask frame lengths asked numpy for exabytes (a MemoryError traceback)."""
    import socket
    import threading

    reply = b"HTTP/1.1 400 Bad Request\r\nconnection: close\r\ncontent-length: 0\r\n\r\n"

    def answer(sock: socket.socket) -> None:
        while True:
            try:
                conn, _ = sock.accept()
            except OSError:  # closed: the test is over
                return
            with conn:
                conn.sendall(reply)

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(8)
        threading.Thread(target=answer, args=(sock,), daemon=True).start()
        address = f"tcp://127.0.0.1:{sock.getsockname()[1]}"
        result = run_cli(numproject, "run", "--scheduler", address, "--connect-timeout", "5", "--force", "src")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"cannot reach the Dask scheduler at {address}: the port answers, but what it says is not Dask's" in (
        result.stderr
    )


# ------------------------------------------------------------------------------------------------ shipping
def shipped(numproject, tmp_path, pipeline="pipeline.yaml", stage="csv", edit=None, store=None):
    """The job of ``stage`` shipped into a store (by default a folder outside the project)."""
    from msflow.api import code_trees_of
    from msflow.runner import Runner
    from msflow.session import open_session
    from msflow.shipping import Shipper
    from msflow.stores import open_store

    session = open_session(numproject / pipeline)
    store = store or open_store(str(tmp_path / "store"))
    runner = Runner(session.pipeline, session.plans, store, session.memo, executor=None, until=stage)
    assert runner.selected == [stage]  # a stage without upstream stages
    job = runner.prepare(stage)
    if edit:
        edit(numproject)
    return Shipper(code_trees_of([session])).ship(job), store


def run_in_fresh_process(job, tmp_path):
    from msflow.executors import ProcessExecutor
    from msflow.jobs import Outcome

    os.environ["MSFLOW_WORKER_CACHE"] = str(tmp_path / "worker-cache")
    pool = ProcessExecutor(1)
    try:
        return Outcome.from_json(pool.submit(job.to_json()).result())
    finally:
        pool.shutdown()
        del os.environ["MSFLOW_WORKER_CACHE"]


def test_a_shipped_job_carries_no_path_and_runs_from_the_store(numproject, tmp_path):
    job, store = shipped(numproject, tmp_path)
    text = job.to_json()
    assert str(numproject) not in text and job.project_root == "" and job.code
    assert job.inputs["table"].files == (("table.csv", "table.csv"),)  # (label, file name)
    moved = tmp_path / "moved"
    numproject.rename(moved)  # the worker cannot use the project folder: it is gone
    outcome = run_in_fresh_process(job, tmp_path)
    assert outcome.status == "ran", outcome.error
    expected = np.loadtxt(moved / "data" / "table.csv", delimiter=",", ndmin=2).reshape(-1)
    assert np.array_equal(store.open(job.key)["x"], expected)


def test_shipping_to_a_fresh_object_store_takes_as_many_requests_for_many_project_modules_as_for_few(
    numproject, tmp_path, s3, monkeypatch
):
    """The modules travel as one pack: the client checks and uploads, and a fresh worker fetches, as many objects
    (and in as many round trips) for a stage importing twelve more modules. One by one, a first run against a fresh
    S3 store spent two serial round trips per project file before its first stage could start, and each worker
    then fetched every file: on the default pipeline 148 of the client's requests and 145 of the workers'."""
    from msflow.shipping import blob_path, materialise_code, open_blobs
    from msflow.stores.objects import S3Objects

    def requests(project):
        waves, paths = [], []
        run, exists, get = S3Objects._run, S3Objects.exists_many, S3Objects.get_many
        monkeypatch.setattr(S3Objects, "_run", lambda self, *args: waves.append(1) or run(self, *args))
        monkeypatch.setattr(S3Objects, "exists_many", lambda self, rels: paths.extend(rels) or exists(self, rels))
        monkeypatch.setattr(S3Objects, "get_many", lambda self, rels: paths.extend(rels) or get(self, rels))
        job, store = shipped(project, tmp_path, store=s3.store(s3.bucket()))
        shipping = (len(waves), len(paths))
        waves.clear()
        paths.clear()
        root = materialise_code(job.code, open_blobs(job.store, job.store_options), tmp_path / f"w-{project.name}")
        fetching = (len(waves), len(paths))
        monkeypatch.setattr(S3Objects, "_run", run)
        monkeypatch.setattr(S3Objects, "exists_many", exists)
        monkeypatch.setattr(S3Objects, "get_many", get)
        shipped_files = {p.relative_to(root) for p in root.rglob("*.py")}
        assert shipped_files == {p.relative_to(project) for p in (project / "numstages").rglob("*.py")}
        assert all((root / rel).read_bytes() == (project / rel).read_bytes() for rel in shipped_files)
        blobs = store.objects.list("blobs/")
        assert {o.path for o in blobs} >= {blob_path(job.code)} | {
            blob_path(d) for d in job.inputs["table"].blobs.values()
        }
        return shipping, fetching, len(blobs)

    few = requests(numproject)
    bigger = tmp_path / "bigger"
    shutil.copytree(numproject, bigger)
    for i in range(12):  # twelve more modules in the stage's import closure
        (bigger / "numstages" / f"extra_{i}.py").write_text(f"VALUE = {i}\n")
    basic = bigger / "numstages" / "basic.py"
    basic.write_text(basic.read_text() + "".join(f"from numstages import extra_{i}  # noqa\n" for i in range(12)))
    many = requests(bigger)
    assert many == few


def test_a_worker_with_other_package_versions_refuses_the_job(numproject, tmp_path):
    from dataclasses import replace

    job, store = shipped(numproject, tmp_path)
    parts = json.loads(json.dumps(job.key_parts))
    assert parts["code"]["dists"]["numpy"].startswith("numpy==")
    parts["code"]["dists"]["numpy"] = "numpy==1.0.0"
    outcome = run_in_fresh_process(replace(job, key_parts=parts), tmp_path)
    assert outcome.status == "failed" and outcome.user_error
    message = outcome.user_error["message"]
    assert "refuses the job: its Python environment differs" in message
    assert f"'numpy': numpy=={np.__version__} here, numpy==1.0.0 in the key" in message
    assert not store.has(job.key)


def test_a_store_folder_the_worker_cannot_reach_is_named(numproject, tmp_path):
    from dataclasses import replace

    job, _ = shipped(numproject, tmp_path)
    outcome = run_in_fresh_process(replace(job, store=str(tmp_path / "elsewhere" / ".msflow")), tmp_path)
    assert outcome.status == "failed" and outcome.user_error
    assert f"cannot use the store folder {tmp_path / 'elsewhere' / '.msflow'}" in outcome.user_error["message"]


def test_code_edited_after_the_key_is_refused(numproject, tmp_path):
    def edit(project):
        path = project / "numstages" / "basic.py"
        path.write_text(path.read_text().replace("ndmin=2).reshape(-1)", "ndmin=2).reshape(-1) * 2"))

    with pytest.raises(UserError, match="numstages/basic.py changed after this run computed its cache keys") as err:
        shipped(numproject, tmp_path, edit=edit)
    assert err.value.file == str(numproject / "numstages" / "basic.py")


def test_a_worker_checks_the_tree_against_the_key_without_parsing(numproject, tmp_path):
    """The tree records its modules' fingerprints (checked by the client against the keys): a job whose key
    names other code is refused; a tree without that record (an older client) is fingerprinted by parsing."""
    from dataclasses import replace

    from msflow.hashing import canonical_json, json_hash
    from msflow.shipping import FolderBlobs, blob_path

    job, store = shipped(numproject, tmp_path)
    parts = json.loads(json.dumps(job.key_parts))
    parts["code"]["modules"]["numstages/basic.py"] = "0" * 32
    other = replace(job, key_parts=parts)
    outcome = run_in_fresh_process(other, tmp_path)
    assert outcome.status == "failed" and outcome.user_error
    assert "does not match the cache key's fingerprint (numstages/basic.py differ)" in outcome.user_error["message"]
    assert not store.has(job.key)
    document = json.loads((tmp_path / "store" / blob_path(job.code)).read_bytes())
    old = {"code": document["code"], "pack": document["pack"]}  # the same files, no record of fingerprints
    FolderBlobs(tmp_path / "store").put(json_hash(old), canonical_json(old).encode())
    assert run_in_fresh_process(replace(job, code=json_hash(old)), tmp_path).status == "ran"


def test_a_code_pack_that_does_not_match_its_tree_is_refused(numproject, tmp_path):
    """The pack is checked module by module against the tree's hashes (a client that packed it wrongly, say)."""
    from dataclasses import replace

    from msflow.hashing import bytes_hash, canonical_json, json_hash
    from msflow.shipping import FolderBlobs, blob_path
    from msflow.stores.packs import Pack, make_pack

    job, _ = shipped(numproject, tmp_path)
    blobs = FolderBlobs(tmp_path / "store")
    document = json.loads((tmp_path / "store" / blob_path(job.code)).read_bytes())
    layout = document["pack"]["files"]
    members = dict(Pack(blobs.get_many([document["pack"]["blob"]])[document["pack"]["blob"]], "pack").members())
    assert len(layout) >= 2 and members[layout[0]] != members[layout[1]]
    members[layout[0]] = members[layout[1]]  # the first module's place holds another module's bytes
    wrong = make_pack(members.items())
    blobs.put(bytes_hash(wrong), wrong)
    document["pack"]["blob"] = bytes_hash(wrong)
    blobs.put(json_hash(document), canonical_json(document).encode())
    outcome = run_in_fresh_process(replace(job, code=json_hash(document)), tmp_path)
    assert outcome.status == "failed" and outcome.user_error
    assert f"the code pack in the store does not hold {layout[0]} as its tree says" in outcome.user_error["message"]


def test_shipped_folder_inputs_and_resources(numproject, tmp_path):
    from dataclasses import replace

    from msflow.shipping import blob_path

    ref, store = shipped(numproject, tmp_path, "resources.yaml", "ref")  # reads a resource beside its module
    assert run_in_fresh_process(ref, tmp_path).status == "ran"
    assert np.array_equal(store.open(ref.key)["v"], np.loadtxt(numproject / "data" / "reference.txt", ndmin=1))
    job, _ = shipped(numproject, tmp_path, "resources.yaml", "folder")
    outcome = run_in_fresh_process(job, tmp_path)
    assert outcome.status == "ran", outcome.error
    parts = sorted((numproject / "data" / "parts").iterdir())
    assert float(store.open(job.key)["total"]) == sum(np.loadtxt(p, ndmin=1).sum() for p in parts)
    (tree,) = job.inputs["folder"].blobs.values()
    blob = tmp_path / "store" / blob_path(tree)
    blob.write_bytes(blob.read_bytes().replace(b"}", b" }", 1))  # corrupt the folder's tree
    shutil.rmtree(tmp_path / "worker-cache")
    again = run_in_fresh_process(replace(job, force=True), tmp_path)
    assert again.status == "failed" and "in the store is corrupt" in again.user_error["message"]


# ------------------------------------------------------------------------------------------------ another machine
def closed_ancestor(path: Path) -> Path | None:
    """The outermost folder above ``path`` that other users cannot enter (e.g. /root), if any."""
    for parent in reversed(path.parents):
        if parent != Path("/") and not parent.stat().st_mode & 0o001:
            return parent
    return None


def outermost(paths):
    paths = sorted({Path(p) for p in paths}, key=lambda p: len(p.parts))
    kept = []
    for path in paths:
        if not any(path.is_relative_to(k) for k in kept):
            kept.append(path)
    return kept


def isolation_script(env_dir: Path, hidden: list[Path], as_nobody: bool) -> str:
    """Shell commands run in a new mount namespace: cover ``hidden`` folders with empty tmpfs mounts, keep the
    Python installation reachable (re-mounted inside a covered closed folder such as /root), drop to nobody."""
    prefixes = outermost(Path(p).resolve() for p in {sys.prefix, sys.base_prefix})
    covered = outermost(hidden + [a for p in prefixes if (a := closed_ancestor(p)) is not None])
    lines = ["set -eu"]
    kept = [(p, env_dir / f"keep{i}") for i, p in enumerate(prefixes) if any(p.is_relative_to(c) for c in covered)]
    for prefix, keep in kept:
        keep.mkdir(exist_ok=True)
        lines.append(f"mount --bind '{prefix}' '{keep}'")
    lines += [f"mount -t tmpfs -o mode=0755,size=1m tmpfs '{folder}'" for folder in covered]
    for prefix, keep in kept:
        lines += [f"mkdir -p '{prefix}'", f"mount --bind '{keep}' '{prefix}'"]
    # --pdeathsig: a killed pytest (a suite timeout) takes its cluster along instead of leaving it running
    drop = f"--reuid={NOBODY} --regid={NOBODY} --clear-groups " if as_nobody else ""
    lines.append(f'exec setpriv {drop}--pdeathsig KILL -- "$@"')
    return "\n".join(lines) + "\n"


class IsolatedCluster:
    """``dask scheduler`` + two ``dask worker`` processes that cannot read the project folders (see module doc)."""

    def __init__(self, hidden: list[Path], extra_env: dict[str, str]):
        for tool in ("unshare", "setpriv", "mount"):
            if shutil.which(tool) is None:
                missing_tool(f"{tool} is not installed: apt-get install -y util-linux mount")
        self.root_user = os.getuid() == 0
        self.env_dir = Path(tempfile.mkdtemp(prefix="msflow-cluster-"))
        self.env_dir.chmod(0o755)
        shutil.copytree(ROOT / "msflow", self.env_dir / "site" / "msflow", ignore=shutil.ignore_patterns("__pycache__"))
        self.work = self.env_dir / "work"
        self.hold = self.env_dir / "hold"
        for folder in (self.work, self.hold):
            folder.mkdir()
            folder.chmod(0o777)
        script = self.env_dir / "isolate.sh"
        unshare = namespace_command()
        self.as_nobody = self.root_user and "--user" not in unshare  # in a user namespace we stay ourselves
        script.write_text(isolation_script(self.env_dir, hidden + [ROOT] + self.source_folders(), self.as_nobody))
        self.prefix = unshare + ["bash", str(script)]
        self.env = {
            "PATH": "/usr/local/bin:/usr/bin:/bin",
            "HOME": str(self.work),
            "LANG": "C.UTF-8",
            "PYTHONPATH": str(self.env_dir / "site"),
            "PYTHONDONTWRITEBYTECODE": "1",
            "AWS_EC2_METADATA_DISABLED": "true",
            "NUMSTAGES_HOLD": str(self.hold),
            "MSFLOW_WORKER_IMPORTS": WORKER_IMPORTS,
            # the BLAS kernel choice (e.g. OPENBLAS_CORETYPE) changes the last bits of results: same as here
            **{k: v for k, v in os.environ.items() if k.startswith(("OPENBLAS_", "MKL_", "NPY_"))},
            **{var: "1" for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")},
            **extra_env,
        }
        self.procs: list[subprocess.Popen] = []
        self.logs: list[Path] = []
        scheduler_file = self.work / "scheduler.json"
        self.start("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file")
        self.address = self.wait_for_address(scheduler_file)
        for n in (1, 2):
            (self.work / f"w{n}").mkdir()
            (self.work / f"w{n}").chmod(0o777)
            self.start(
                "worker", "--scheduler-file", str(scheduler_file), "--nthreads", "1", "--nworkers", "1",
                "--preload-nanny", "msflow.dask_setup", "--preload", "msflow.dask_setup",
                "--local-directory", str(self.work / f"w{n}"),
                "--no-dashboard", "--name", f"w{n}",
            )  # fmt: skip
        from distributed import Client

        self.client = Client(self.address, timeout=60, set_as_default=False)
        try:
            self.client.wait_for_workers(2, timeout=120)
        except Exception as exc:
            self.close()
            pytest.fail(f"the workers did not start ({exc}): {self.log_text()}")

    @staticmethod
    def source_folders() -> list[Path]:
        """Folders on sys.path outside the Python installation (checkouts installed with ``pip install -e``)."""
        prefixes = [Path(p).resolve() for p in {sys.prefix, sys.base_prefix}]
        found = []
        for entry in sys.path:
            path = Path(entry or ".").resolve()
            if path.is_dir() and not any(path.is_relative_to(p) for p in prefixes) and path != Path("/"):
                found.append(path)
        return found

    def start(self, role: str, *args: str) -> None:
        log = self.env_dir / f"{role}{len(self.procs)}.log"
        self.logs.append(log)
        if role == "scheduler":
            args = (*args, str(self.work / "scheduler.json"))
        with open(log, "wb") as out:
            self.procs.append(
                subprocess.Popen(
                    [*self.prefix, sys.executable, "-m", "dask", role, *args],
                    cwd=self.work,
                    env=self.env,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                )
            )

    def wait_for_address(self, scheduler_file: Path) -> str:
        deadline = time.monotonic() + 120  # a guard against hanging, not a speed assertion
        while time.monotonic() < deadline:
            if self.procs[0].poll() is not None:
                pytest.fail(f"the scheduler exited: {self.log_text()}")
            try:
                return str(json.loads(scheduler_file.read_text())["address"])
            except (OSError, ValueError, KeyError):
                time.sleep(0.05)
        pytest.fail(f"the scheduler never wrote {scheduler_file}: {self.log_text()}")

    def log_text(self) -> str:
        return "\n".join(f"--- {log.name}\n{log.read_text(errors='replace')[-3000:]}" for log in self.logs)

    def worker_pids(self) -> dict[str, int]:
        return self.client.run(os.getpid)

    def close(self) -> None:
        self.client.close()
        for proc in reversed(self.procs):
            with_group(proc, signal.SIGTERM)
        for proc in reversed(self.procs):
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                with_group(proc, signal.SIGKILL)
                proc.wait()
        shutil.rmtree(self.env_dir, ignore_errors=True)


def namespace_command() -> list[str]:
    """``unshare`` for a private mount namespace: directly as root, else (or where root lacks CAP_SYS_ADMIN, as
    in a default container) inside a new user namespace."""
    for command in (
        ["unshare", "--mount", "--propagation", "private"],
        ["unshare", "--user", "--map-root-user", "--mount", "--propagation", "private"],
    ):
        if subprocess.run([*command, "true"], capture_output=True).returncode == 0:
            return command
    missing_tool(
        "cannot create a mount namespace (unshare --mount, also in a user namespace), so no worker can be kept from "
        "reading the project folder: run as root, or allow unprivileged user namespaces "
        "(sysctl -w kernel.unprivileged_userns_clone=1 user.max_user_namespaces=15000)"
    )


def with_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    cluster = IsolatedCluster(hidden=[tmp_path_factory.getbasetemp()], extra_env={})
    try:
        yield cluster
    finally:
        cluster.close()


def test_worker_preload_reports_modules_it_cannot_import(caplog):
    from msflow.dask_setup import extra_modules, warm_imports

    assert extra_modules(" scipy.signal, cv2  av,") == ["scipy.signal", "cv2", "av"]
    failed = warm_imports(["json", "no_such_module_for_msflow"])
    assert (
        list(failed) == ["no_such_module_for_msflow"] and "ModuleNotFoundError" in failed["no_such_module_for_msflow"]
    )
    assert "could not pre-import no_such_module_for_msflow" in caplog.text


@pytest.mark.cluster
def test_workers_start_with_their_imports_done(cluster):
    """The worker preload imported msflow's worker path and MSFLOW_WORKER_IMPORTS before the first job."""

    def loaded():
        import sys

        wanted = ("msflow.worker", "msflow.plan", "pydantic", "zarr", "cv2", "scipy.signal", "parselmouth")
        return sorted(m for m in wanted if m in sys.modules)

    assert set(map(tuple, cluster.client.run(loaded).values())) == {
        ("cv2", "msflow.plan", "msflow.worker", "parselmouth", "pydantic", "scipy.signal", "zarr")
    }


@pytest.mark.cluster
def test_the_workers_are_another_machine(cluster, numproject):
    """What the stand-in guarantees: another user (as root), another folder, no project, no checkout."""
    uids = cluster.client.run(os.getuid)
    assert len(uids) == 2 and (set(uids.values()) == {NOBODY} or not cluster.as_nobody)
    assert set(cluster.client.run(os.getcwd).values()) == {str(cluster.work)}
    for folder in (numproject, ROOT / "stages", ROOT / "msflow"):
        assert set(cluster.client.run(os.path.exists, str(folder)).values()) == {False}

    def listing(folder: str):  # defined here: cloudpickle ships it by value (the tests are not on the workers)
        try:
            return tuple(sorted(os.listdir(folder)))
        except PermissionError:
            return "permission denied"

    # covered by an empty mount, or (as nobody, under a closed folder such as a mktemp -d) not even reachable
    assert set(cluster.client.run(listing, str(ROOT)).values()) <= {(), "permission denied"}
    assert set(cluster.client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_").values()) == {None}


@pytest.mark.cluster
def test_default_pipeline_on_the_cluster_matches_local(cluster, s3, default_run, tmp_path):
    local_dir, local = default_run
    proj = copy_project(tmp_path / "proj")
    on_s3(proj, s3, s3.bucket(), files=("pipeline.yaml",))
    result = msflow.run(proj / "pipeline.yaml", scheduler=cluster.address, jobs=2)
    workers = set(cluster.client.scheduler_info()["workers"])
    assert sorted(result.executed) == sorted(local.states)
    ours, theirs = result.record["stages"], local.record["stages"]
    # every output, the MP4 videos included: their encoder runs on one thread (stages/formats/video.py), so its
    # bytes do not depend on the cores of the machine (the edit's video, with x264's default threads, did)
    for name, stage in ours.items():
        assert stage["worker"] in workers and stage["attempts"] == 1
        assert stage["outputs"] == theirs[name]["outputs"], name
        assert stage["key"] == theirs[name]["key"], name
    for published in local.session.pipeline.publish.values():
        assert (proj / published).read_bytes() == (local_dir / published).read_bytes()


@pytest.mark.cluster
def test_sweep_on_the_cluster_matches_local(cluster, s3, numproject, tmp_path):
    from msflow.sweep import expand_variants, run_sweep

    variants = expand_variants(["src.n=3,4", "scaled.factor=2,5"], None)
    local_dir = tmp_path / "local"
    shutil.copytree(numproject, local_dir)
    local = run_sweep(local_dir / "pipeline.yaml", variants)
    url = on_s3(numproject, s3, s3.bucket(), files=("pipeline.yaml",))
    remote = run_sweep(numproject / "pipeline.yaml", variants, scheduler=cluster.address, jobs=2)
    assert remote.executed == local.executed and all(v.ok for v in remote.variants)
    local_store, remote_store = open_store(str(local_dir / ".msflow")), open_store(url, s3.options)
    for ours, theirs in zip(remote.variants, local.variants):
        a, b = remote_store.read_run(ours.run_id), local_store.read_run(theirs.run_id)
        assert {n: (s["key"], s["outputs"]) for n, s in a["stages"].items()} == {
            n: (s["key"], s["outputs"]) for n, s in b["stages"].items()
        }


@pytest.mark.cluster
def test_worker_killed_mid_stage_on_the_cluster(cluster, s3, numproject):
    bucket = s3.bucket()
    (numproject / "hold.yaml").write_text(
        "version: 1\nstages:\n  src:\n    uses: numstages.basic:Source\n"
        "  slow:\n    uses: numstages.basic:Slow\n    inputs: {x: src.x}\n    params: {size: 1000}\n"
    )
    on_s3(numproject, s3, bucket, files=("hold.yaml",))
    hold = Hold(cluster.hold)
    proc = start_cli(numproject, "run", "hold.yaml", "--scheduler", cluster.address)
    try:
        stage, pid = hold.wait_ready(proc).split()
        assert stage == "slow" and int(pid) in cluster.worker_pids().values()
        os.kill(int(pid), signal.SIGKILL)  # the worker dies mid-stage
        hold.release()  # the retry passes the hold point
        _, stderr = proc.communicate(timeout=300)
    finally:
        proc.kill()
        for name in ("ready", "release"):
            (cluster.hold / name).unlink(missing_ok=True)
    assert proc.returncode == 0, stderr
    assert "retrying (attempt 2): worker tcp://" in stderr and "was lost" in stderr
    store = s3.store(bucket, "num")
    (run_id,) = store.run_ids()
    record = store.read_run(run_id)
    assert record["stages"]["slow"]["attempts"] == 2 and record["stages"]["slow"]["state"] == "ran"
    assert "attempt 2: 1 worker(s) lost mid-stage" in record["stages"]["slow"]["detail"]
    assert not uncommitted_folders(store)
    assert store.verify(record["stages"]["slow"]["key"]) == []
    assert store.open(record["stages"]["slow"]["key"])["small"].tolist() == list(range(10))


def test_remote_store_keeps_the_order_of_meta_mappings(s3):
    """Stages may index arrays by the order of a meta mapping (the blend's regions): a remote store must read it
    back as written, as a local store does, or a cluster run computes something else."""
    store = s3.store(s3.bucket())
    meta = {"regions": {"mouth": [0, 1], "eyes": [2], "brows": [3]}, "b": 1, "a": 2}
    store.write("0" * 32, {"x": np.zeros(3)}, {"meta": meta, "metrics": {}, "key": "0" * 32, "stage": "s"})
    fresh = open_store(store.url, s3.options)
    read = fresh.open("0" * 32).meta
    assert list(read) == ["regions", "b", "a"] and list(read["regions"]) == ["mouth", "eyes", "brows"]
