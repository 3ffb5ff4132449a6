"""Test-wide settings and shared helpers: one BLAS thread per process (CI has 2 cores), the project root on
sys.path, subprocess helpers for the CLI, and outside tools (npm packages, Chromium) for the tests that need them.

Outside tools (interface for every area's tests):

- ``missing_tool(reason)``: skip with ``reason`` (which must hold the exact install command), or fail when the
  ``CI`` environment variable is set (CI installs everything; a skip there would hide a broken set-up).
- ``node_modules`` (session fixture): the ``node_modules`` folder holding the npm packages in ``NPM_PACKAGES``
  (the Khronos glTF validator, three.js), installed once with npm into a cache folder outside the project
  (``$XDG_CACHE_HOME/msflow-npm``, default ``~/.cache/msflow-npm``; ``MSFLOW_NPM_CACHE`` overrides) when Node.js
  is present. It also sets ``MSFLOW_NODE_MODULES`` for the session, so code that looks the validator up by
  itself (``stages.formats.gltf.validate_glb``) finds it. Request it in any test that validates a GLB.
- ``chromium`` (session fixture): the path of the Chromium executable (``CHROMIUM``) for Playwright.
- ``blender`` (session fixture): the path of Debian's Blender, with the numpy its glTF importer needs.
"""

import contextlib
import fcntl
import logging
import os
import shutil
import subprocess
import sys
import time
import uuid
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


#: processes start_cli started and holds made during the current test, ended when it ends (a test that fails
#: before releasing its hold would otherwise leave its run, and the run's workers, waiting forever)
_STARTED: list[subprocess.Popen] = []
_HOLDS: list["Hold"] = []


def start_cli(cwd, *args, env=None):
    """Start ``python -m msflow.cli ARGS`` in the background (stdout and stderr piped, text)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "msflow.cli", *map(str, args)],
        cwd=cwd,
        env=cli_env(env),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    _STARTED.append(proc)
    return proc


@pytest.fixture(autouse=True)
def _end_started_processes():
    """After each test: release its holds, then stop what it started and left running (SIGTERM, so a run stops
    its pool's workers too; SIGKILL if that does not end it)."""
    yield
    for hold in _HOLDS:
        with contextlib.suppress(OSError):
            hold.release()
    for proc in _STARTED:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
    _STARTED.clear()
    _HOLDS.clear()


class Hold:
    """A kill point: a numstages stage started with ``env`` (NUMSTAGES_HOLD=folder) writes ``ready`` and then
    waits for ``release``. Synchronisation by files, never by sleeping a guessed time."""

    def __init__(self, folder):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.env = {"NUMSTAGES_HOLD": str(self.folder)}
        _HOLDS.append(self)

    def wait_ready(self, proc, timeout=120):
        """Block until the held stage is waiting (fails if ``proc`` exits first); returns the stage's line."""
        ready = self.folder / "ready"
        deadline = time.monotonic() + timeout  # a guard against hanging, not a speed assertion
        while not ready.exists():
            if proc.poll() is not None:
                pytest.fail(f"the run ended before reaching the hold point: {proc.communicate()}")
            if time.monotonic() > deadline:
                proc.kill()
                pytest.fail("the run never reached the hold point")
            time.sleep(0.01)
        return ready.read_text()

    def release(self):
        (self.folder / "release").write_text("go")


def process_running(pid):
    """True while process ``pid`` runs; a zombie counts as ended (an orphan's parent, the container's init, may
    never reap it)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
    except OSError:  # no /proc
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True


def wait_for_line(proc, text, timeout=120):
    """Read ``proc``'s stderr until a line containing ``text`` (fails if it ends first); returns the lines read."""
    import selectors

    lines = []
    deadline = time.monotonic() + timeout  # a guard against hanging, not a speed assertion
    with selectors.DefaultSelector() as selector:
        selector.register(proc.stderr, selectors.EVENT_READ)
        while time.monotonic() < deadline:
            if not selector.select(timeout=1.0):
                continue
            line = proc.stderr.readline()
            if not line:
                pytest.fail(f"stderr ended before {text!r}: {lines}")
            lines.append(line)
            if text in line:
                return lines
    proc.kill()
    pytest.fail(f"no line with {text!r} on stderr: {lines}")


@pytest.fixture(scope="session")
def default_run(tmp_path_factory):
    """The repository's default pipeline, run once per session in a copy with its own store."""
    import msflow

    dest = copy_project(tmp_path_factory.mktemp("repo") / "msflow")
    return dest, msflow.run(dest / "pipeline.yaml")


def copy_project(dest: Path, names=("pipeline.yaml", "data", "stages", "pyproject.toml")) -> Path:
    """Copy the repository's ``names`` (files or folders, without bytecode caches) into a new folder ``dest``."""
    dest.mkdir(parents=True)
    for name in names:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(src, dest / name)
    return dest


# ------------------------------------------------------------------------------------------------ outside tools
NPM_PACKAGES = ("gltf-validator@2.0.0-dev.3.10", "three@0.170.0")
NPM_INSTALL = f"npm install --no-save --no-package-lock {' '.join(NPM_PACKAGES)}"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_INSTALL = "apt-get update && apt-get install -y chromium"
BLENDER_INSTALL = "apt-get update && apt-get install -y blender python3-numpy"


def missing_tool(reason):
    """Skip for a missing outside tool (``reason`` holds the install command); fail instead when CI is set."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason} (CI is set: outside tools must be installed)")
    pytest.skip(reason)


def npm_cache():
    """Where the npm packages of the tests are installed: outside the project, shared by checkouts."""
    if os.environ.get("MSFLOW_NPM_CACHE"):
        return Path(os.environ["MSFLOW_NPM_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "msflow-npm"


def npm_installed(modules):
    return all((modules / spec.rsplit("@", 1)[0] / "package.json").is_file() for spec in NPM_PACKAGES)


def install_npm_packages(cache: Path, modules: Path) -> None:
    """npm install NPM_PACKAGES into ``cache``, one test process at a time (pytest-xdist runs several): the
    second finds them installed under the lock."""
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / ".install-lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if npm_installed(modules):
            return
        proc = subprocess.run([*NPM_INSTALL.split(), "--silent"], cwd=cache, capture_output=True, text=True)
    if proc.returncode != 0 or not npm_installed(modules):
        missing_tool(f"npm could not install {NPM_PACKAGES} ({proc.stderr[-300:]}); run in {cache}: {NPM_INSTALL}")


@pytest.fixture(scope="session")
def node_modules():
    """The node_modules folder with NPM_PACKAGES, installed once into the npm cache folder when Node.js is present;
    MSFLOW_NODE_MODULES points at it for the rest of the session."""
    cache = npm_cache()
    modules = cache / "node_modules"
    if not npm_installed(modules):
        if shutil.which("node") is None or shutil.which("npm") is None:
            missing_tool("Node.js is not installed: apt-get install -y nodejs npm")
        install_npm_packages(cache, modules)
    previous = os.environ.get("MSFLOW_NODE_MODULES")
    os.environ["MSFLOW_NODE_MODULES"] = str(modules)
    yield modules
    if previous is None:
        os.environ.pop("MSFLOW_NODE_MODULES", None)
    else:
        os.environ["MSFLOW_NODE_MODULES"] = previous


@pytest.fixture(scope="session")
def chromium():
    """The Chromium executable Playwright drives (Debian's package; Playwright downloads no browser)."""
    try:
        import playwright  # noqa: F401
    except ImportError:
        missing_tool('Playwright is not installed: pip install -e ".[test]"')
    if not os.access(CHROMIUM, os.X_OK):
        missing_tool(f"Chromium is not installed: {CHROMIUM_INSTALL} ({CHROMIUM})")
    return CHROMIUM


def blender_env() -> dict:
    """The environment to start Blender in: PATH without this interpreter's folder, since Blender's embedded
    Python takes its standard library from the first ``python3`` on PATH, and a virtualenv's or pyenv's would
    hide the system's packages (numpy among them) from it."""
    ours = {os.path.dirname(sys.executable), os.path.dirname(os.path.realpath(sys.executable))}
    path = [p for p in os.environ.get("PATH", "").split(os.pathsep) if p and p not in ours]
    return {**os.environ, "PATH": os.pathsep.join(path)}


@pytest.fixture(scope="session")
def blender():
    """Blender's executable, checked to start headless with numpy (Debian's glTF importer needs python3-numpy)."""
    path = shutil.which("blender")
    if path is None:
        missing_tool(f"Blender is not installed: {BLENDER_INSTALL}")
    check = [path, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", "import numpy"]
    proc = subprocess.run(check, capture_output=True, text=True, timeout=120, env=blender_env())
    if proc.returncode != 0:
        missing_tool(f"Blender cannot import numpy ({proc.stdout[-300:]}): {BLENDER_INSTALL}")
    return path


# ------------------------------------------------------------------------------------------------ object store
class MotoS3:
    """A moto S3 server on loopback: its endpoint, store options with dummy credentials and a boto3 client."""

    def __init__(self, endpoint: str):
        import boto3

        self.endpoint = endpoint
        self.options = {"endpoint_url": endpoint, "key": "testing", "secret": "testing"}
        self.client = boto3.client(
            "s3",
            endpoint_url=endpoint,
            aws_access_key_id="testing",
            aws_secret_access_key="testing",
            region_name="us-east-1",
        )

    def bucket(self) -> str:
        name = f"b-{uuid.uuid4().hex[:12]}"
        self.client.create_bucket(Bucket=name)
        return name

    def objects(self, bucket: str, prefix: str = "") -> list[str]:
        keys, token = [], None
        while True:
            kwargs = {"Bucket": bucket, "Prefix": prefix, **({"ContinuationToken": token} if token else {})}
            resp = self.client.list_objects_v2(**kwargs)
            keys += [o["Key"] for o in resp.get("Contents", [])]
            if not resp.get("IsTruncated"):
                return keys
            token = resp["NextContinuationToken"]

    def store(self, bucket: str, prefix: str = "p"):
        from msflow.stores import open_store

        return open_store(f"s3://{bucket}/{prefix}", self.options)


def damage_chunk(store, key: str, rel: str | None = None) -> str:
    """Flip a byte in the middle of one stored chunk (``rel`` in the group, else the largest) of artifact ``key``
    on a remote store, whether its group is loose objects or one pack (msflow.stores.packs; the pack is rebuilt,
    so only msflow's own chunk checksum can notice); returns the chunk's path in the group."""
    from msflow.stores.packs import Pack, make_pack

    def flip(data: bytes) -> bytes:
        damaged = bytearray(data)
        damaged[len(damaged) // 2] ^= 0x10
        return bytes(damaged)

    marker = store._marker(key)
    folder = store.data_path(key, marker["data"])
    if marker.get("pack"):
        path = f"{folder}/{marker['pack']}"
        members = dict(Pack(store.objects.get(path), path).members())
        rel = rel or max((r for r in members if not r.endswith("zarr.json")), key=lambda r: len(members[r]))
        store.objects.put(path, make_pack([(r, flip(d) if r == rel else d) for r, d in members.items()]))
        return rel
    sizes = {o.path[len(folder) + 1 :]: o.size for o in store.objects.list(folder + "/") if "/c" in o.path}
    rel = rel or max(sizes, key=lambda r: sizes[r])
    store.objects.put(f"{folder}/{rel}", flip(store.objects.get(f"{folder}/{rel}")))
    return rel


@pytest.fixture(scope="module")
def s3():
    """A moto S3 server on 127.0.0.1 for the module's tests (instance metadata lookups off: botocore stays local)."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    os.environ["AWS_EC2_METADATA_DISABLED"] = "true"
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield MotoS3(f"http://{host}:{port}")
    server.stop()
