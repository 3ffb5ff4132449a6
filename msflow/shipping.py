"""Shipping jobs to workers that share nothing with the project but the store and a Python environment.

A worker on another machine cannot read the project folder, so a job sent to a Dask scheduler carries no paths:

- **Code by content.** The project's code that the run's stages need (every module of each stage's import closure,
  and the data files stages declare in ``Stage.resources``) is put into the store as content-addressed blobs, plus
  one small *code tree* (relative path -> content hash, and each module's fingerprint) whose own hash names it.
  The modules travel as one blob, the tree's *pack* (a zip of them, as msflow.stores.packs makes), so a
  fresh store or worker costs the same few requests however many modules the stages import; each resource (models,
  meshes: large, and rarely changed) is a blob of its own, so an edit to the code uploads none of them again.
  Building the tree, the client fingerprints every module it ships (the planner's digest while the file's stat
  signature is unchanged, else parsed from the bytes shipped) against the key's ``code.modules``: code edited
  between key and shipping is refused, never computed under the old key. The job carries the tree's hash; the
  worker rebuilds the tree once in its cache (``worker_cache``), checks the stage's closure in the key against the
  tree's fingerprints (no parsing: the blobs are checked by content) and imports the stage from there.
- **Data files by content.** An ``Input.files`` input becomes blobs (a file: its bytes, whose hash is the one in the
  key; a folder: a JSON tree of its files' hashes, whose hash is the folder's hash in the key). The worker rebuilds
  each under its cache with its original file name, so stages see ordinary paths.
- **The environment is checked, not assumed.** The key holds the Python version and the versions of the
  distributions the code imports; a worker whose environment differs refuses the job with a ``UserError`` naming
  the worker and each difference, instead of computing a different result under the same key.

Blobs live under ``blobs/`` of the store (an object store, or a store folder on a shared file system). They are
immutable and named by the xxh3-128 of their content, so a run uploads only what the store does not have yet and
a worker checks every blob it reads.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import tempfile
import threading
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from msflow.errors import UserError
from msflow.hashing import bytes_hash, canonical_json, file_hash, json_hash, stat_signature
from msflow.jobs import Job, JobInput

if TYPE_CHECKING:
    from msflow.fingerprint import CodeIndex
    from msflow.plan import StagePlan
    from msflow.stage import Files
    from msflow.stores.objects import Objects


# ---------------------------------------------------------------------------------------------------------- blobs
UPLOAD_BATCH_BYTES = 64 << 20  # files read into memory at a time when shipping them


class Blobs(Protocol):
    """Content-addressed, immutable blobs beside a store's artifacts."""

    def has(self, digest: str) -> bool: ...
    def missing(self, digests: list[str]) -> list[str]: ...
    def put(self, digest: str, data: bytes) -> None: ...
    def put_many(self, items: dict[str, bytes]) -> None: ...
    def get_many(self, digests: list[str]) -> dict[str, bytes | None]: ...


def blob_path(digest: str) -> str:
    """Where a blob lives, relative to the store's root."""
    return f"blobs/{digest[:2]}/{digest}"


class ObjectBlobs:
    """Blobs on an object store (``s3://...``, any fsspec URL), through the store's object primitives."""

    def __init__(self, objects: Objects):
        self.objects = objects

    def has(self, digest: str) -> bool:
        return not self.missing([digest])

    def missing(self, digests: list[str]) -> list[str]:
        """The digests not in the store, asked for concurrently."""
        found = self.objects.exists_many([blob_path(d) for d in digests])
        return [d for d in digests if not found[blob_path(d)]]

    def put(self, digest: str, data: bytes) -> None:
        self.objects.put(blob_path(digest), data)

    def put_many(self, items: dict[str, bytes]) -> None:
        self.objects.put_many({blob_path(d): data for d, data in items.items()})

    def get_many(self, digests: list[str]) -> dict[str, bytes | None]:
        found = self.objects.get_many([blob_path(d) for d in digests])
        return {d: found[blob_path(d)] for d in digests}


class FolderBlobs:
    """Blobs in a store folder (a local or shared POSIX file system)."""

    def __init__(self, root: Path):
        self.root = root

    def has(self, digest: str) -> bool:
        return (self.root / blob_path(digest)).is_file()

    def missing(self, digests: list[str]) -> list[str]:
        return [d for d in digests if not self.has(d)]

    def put(self, digest: str, data: bytes) -> None:
        from msflow.atomic import write_atomic

        path = self.root / blob_path(digest)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, data)

    def put_many(self, items: dict[str, bytes]) -> None:
        for digest, data in items.items():
            self.put(digest, data)

    def get_many(self, digests: list[str]) -> dict[str, bytes | None]:
        found: dict[str, bytes | None] = {}
        for digest in digests:
            try:
                found[digest] = (self.root / blob_path(digest)).read_bytes()
            except FileNotFoundError:
                found[digest] = None
        return found


def open_blobs(url: str, options: dict[str, Any]) -> Blobs:
    """The blobs of the store at ``url`` (the job's ``store`` and ``store_options``)."""
    if url.startswith("file://"):
        url = url[len("file://") :]
    if "://" in url:
        from msflow.stores.objects import make_objects

        return ObjectBlobs(make_objects(url, options))
    return FolderBlobs(Path(url))


def fetch_verified(blobs: Blobs, digests: list[str]) -> dict[str, bytes]:
    """Blobs by hash; a missing blob, or one whose content does not hash to its name, is an error."""
    found = blobs.get_many(sorted(set(digests)))
    out = {}
    for digest, data in found.items():
        if data is None:
            raise UserError(f"blob {digest} is missing from the store; run again from the project to upload it")
        if bytes_hash(data) != digest:
            raise UserError(f"blob {digest} in the store is corrupt (its content hashes differently)")
        out[digest] = data
    return out


# ---------------------------------------------------------------------------------------------------------- client
@dataclass
class CodeTree:
    """The project code a run's stages need: relative path -> content hash, and where each file is here;
    ``modules``: each module's fingerprint (AST digest), checked against the keys' when the tree was made."""

    files: dict[str, str]
    sources: dict[str, Path]
    modules: dict[str, str] = field(default_factory=dict)
    module_bytes: dict[str, bytes] = field(default_factory=dict, repr=False)  # the modules' content, as hashed

    @cached_property
    def pack(self) -> bytes:
        """The modules as one zip (msflow.stores.packs), member name = relative path."""
        from msflow.stores.packs import make_pack

        return make_pack((rel, self.module_bytes[rel]) for rel in sorted(self.module_bytes))

    @cached_property
    def document(self) -> dict[str, Any]:
        document: dict[str, Any] = {
            "code": dict(sorted(self.files.items())),
            "modules": dict(sorted(self.modules.items())),
        }
        if self.module_bytes:
            document["pack"] = {"blob": bytes_hash(self.pack), "files": sorted(self.module_bytes)}
        return document

    @cached_property
    def digest(self) -> str:
        return json_hash(self.document)


def code_tree(root: Path, plans: Iterable[StagePlan], memo: dict[str, Any] | None = None) -> CodeTree:
    """Every module in the stages' import closures and every declared resource, relative to the project root
    (modules of development packages outside it: relative to their package's folder, as fingerprints name them).

    Each module's bytes are fingerprinted again and must give the digest its stage's key holds: code edited after
    the keys were computed is refused here, so workers need not parse the code again. ``memo`` (the session's
    code memo) keeps the digests by content hash, so an unchanged file is parsed once, not once per run."""
    from msflow.fingerprint import CodeIndex

    index = CodeIndex(root)
    known: dict[str, str] = dict((memo or {}).get("shipped", {}))
    planned: dict[str, list[Any]] = (memo or {}).get("files", {})
    sources: dict[str, Path] = {}
    files: dict[str, str] = {}
    modules: dict[str, str] = {}
    module_bytes: dict[str, bytes] = {}
    digests: dict[str, str] = {}  # content hash -> AST digest, of this tree's modules
    for plan in plans:
        for rel, wanted in plan.code["modules"].items():
            if rel not in modules:
                path = sources[rel] = module_source(index, root, rel)
                data = module_bytes[rel] = path.read_bytes()
                content, digest = module_fingerprint(path, data, known, planned.get(rel))
                files[rel], modules[rel], digests[content] = content, digest, digest
                known[content] = digest
            if modules[rel] != wanted:
                raise UserError(
                    f"{rel} changed after this run computed its cache keys; run again",
                    stage=plan.name,
                    file=str(sources[rel]),
                )
        for name, rel in plan.interface.get("resources", {}).items():
            path = root / rel
            if Path(rel).is_absolute() or rel.startswith("../"):
                path, rel = Path(rel).resolve(), resource_rel(plan, name, Path(rel).resolve())
            sources[rel] = path
    files.update({rel: file_hash(path) for rel, path in sorted(sources.items()) if rel not in files})
    if memo is not None:
        memo["shipped"] = digests  # only the current tree's: the memo does not grow with every edit
    return CodeTree(dict(sorted(files.items())), sources, modules, module_bytes)


def module_fingerprint(path: Path, data: bytes, known: dict[str, str], planned: list[Any] | None) -> tuple[str, str]:
    """(content hash, AST digest) of a module file's ``data``: the digest from ``known`` (content hash -> digest),
    else the planner's (``planned``: its memo entry [stat signature, digest, imports]) when the file's stat
    signature, taken after reading it, is still the one the planner fingerprinted, else parsed from ``data``."""
    from msflow.fingerprint import parse_module

    content = bytes_hash(data)
    digest = known.get(content)
    if digest is None and planned and planned[0] == stat_signature(path):
        digest = str(planned[1])
    if digest is None:
        try:
            digest = parse_module(data, str(path))[0]
        except SyntaxError as exc:
            raise UserError(f"syntax error at line {exc.lineno}: {exc.msg}", file=str(path)) from None
    return content, digest


def resource_rel(plan: StagePlan, name: str, path: Path) -> str:
    """Where a resource outside the project root sits in the code tree: relative to the folder its stage's modules
    were imported from (a development package's folder), found as the nearest folder above it that holds them;
    stages locate resources relative to their own modules, so the tree must keep that layout."""
    anchor = next(iter(plan.code["modules"]), None)
    for parent in path.parents:
        if anchor is not None and (parent / anchor).is_file():
            return path.relative_to(parent).as_posix()
    raise UserError(
        f"{plan.uses} reads the data file {path} (resource '{name}') from outside its code's folder, so it cannot "
        "be shipped to the Dask workers: keep resources beside the stage's package",
        stage=plan.name,
        field="uses",
    )


def module_source(index: Any, root: Path, rel: str) -> Path:
    """The file of a fingerprinted module: in the project, or in a development package's folder."""
    path = root / rel
    if path.is_file():
        return path
    top = rel.split("/")[0].removesuffix(".py")
    folder = index.source_root(top)
    if folder is not None and (Path(folder) / rel).is_file():
        return Path(folder) / rel
    raise UserError(f"cannot find the module file {rel} to ship to the Dask workers")


class Shipper:
    """Rewrites jobs for workers that cannot read the project: code and data files become blobs in the store.

    ``trees`` maps a project root to the code tree of the run's stages there (computed on first use). Blobs known
    to be in the store are remembered, so each is checked or uploaded once per run."""

    def __init__(self, trees: Any):
        self.trees = trees
        self.known: set[str] = set()
        self.lock = threading.Lock()

    def ship(self, job: Job) -> Job:
        with self.lock:
            blobs = open_blobs(job.store, job.store_options)
            tree = self.trees(job.project_root)
            self.upload_code(blobs, tree)
            inputs = {
                name: self.ship_files(blobs, job, name, entry) if entry is not None and entry.kind == "files" else entry
                for name, entry in job.inputs.items()
            }
        return replace(job, project_root="", code=tree.digest, inputs=inputs)

    def upload_code(self, blobs: Blobs, tree: CodeTree) -> None:
        """The tree's pack and resources, then the tree itself (so a tree in the store implies the rest is)."""
        document = tree.document
        if tree.digest in self.known or blobs.has(tree.digest):
            self.known.add(tree.digest)
            return
        resources = [
            (d, tree.sources[rel], f"project file {rel}")
            for rel, d in tree.files.items()
            if rel not in tree.module_bytes
        ]
        pack = {document["pack"]["blob"]: tree.pack} if "pack" in document else {}
        self.upload_files(blobs, resources, pack)
        blobs.put(tree.digest, canonical_json(document).encode())
        self.known.add(tree.digest)

    def upload_files(
        self, blobs: Blobs, files: list[tuple[str, Path, str]], read: dict[str, bytes] | None = None
    ) -> None:
        """Files (digest, path, what) and blobs already ``read`` (digest -> bytes) into the store: the store asked
        once which it lacks (concurrently, on an object store), those uploaded together in batches of about
        UPLOAD_BATCH_BYTES. One by one, a first run against a fresh S3 store spent two serial round trips per
        project file before its first stage could start."""
        wanted: dict[str, tuple[Path, str] | None] = {d: (path, what) for d, path, what in files if d not in self.known}
        wanted.update({digest: None for digest in read or {} if digest not in self.known})
        batch: dict[str, bytes] = {}
        size = 0
        for digest in blobs.missing(list(wanted)) if wanted else ():
            source = wanted[digest]
            if source is None:
                data = (read or {})[digest]
            else:
                path, what = source
                data = path.read_bytes()
                if bytes_hash(data) != digest:
                    raise UserError(f"{what} changed during the run; run again", file=str(path))
            batch[digest] = data
            size += len(data)
            if size >= UPLOAD_BATCH_BYTES:
                blobs.put_many(batch)
                batch, size = {}, 0
        if batch:
            blobs.put_many(batch)
        self.known.update(wanted)

    def ship_files(self, blobs: Blobs, job: Job, name: str, entry: JobInput) -> JobInput:
        """A data-files input as blobs: each labelled file (or folder tree) by the content hash the key holds."""
        part = ((job.key_parts or {}).get("inputs") or {}).get(name) or {}
        hashes: dict[str, str] = part.get("files", {})
        names, folders = [], []
        for label, path in entry.files:
            digest = hashes[label]
            where = f"stage '{job.stage}' inputs.{name}.{label}"
            if os.path.isdir(path):
                self.upload_folder(blobs, digest, Path(path), where)
                folders.append(label)
            else:
                self.upload_files(blobs, [(digest, Path(path), f"the data file of {where}")])
            names.append((label, Path(path).name))
        return replace(entry, files=tuple(names), blobs=dict(hashes), folders=tuple(folders))

    def upload_folder(self, blobs: Blobs, digest: str, folder: Path, where: str) -> None:
        """A folder input: its files, then its tree ``{"folder": {relpath: hash}}`` (hashed as the key hashed it)."""
        if digest in self.known or blobs.has(digest):
            self.known.add(digest)
            return
        entries = folder_entries(folder)
        document = {"folder": {rel: file_hash(folder / rel) for rel in entries}}
        if json_hash(document) != digest:
            raise UserError(f"the data folder of {where} changed during the run; run again", file=str(folder))
        self.upload_files(
            blobs, [(d, folder / rel, f"{rel} in the data folder of {where}") for rel, d in document["folder"].items()]
        )
        blobs.put(digest, canonical_json(document).encode())
        self.known.add(digest)


def folder_entries(folder: Path) -> list[str]:
    """A folder input's files as the key sees them (msflow.hashing.FileHashMemo): relative paths, hidden skipped."""
    found = []
    for dirpath, dirnames, files in os.walk(folder):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in sorted(files):
            if not name.startswith("."):
                found.append(os.path.relpath(os.path.join(dirpath, name), folder).replace(os.sep, "/"))
    return found


# ---------------------------------------------------------------------------------------------------------- worker
def worker_cache() -> Path:
    """Where a worker keeps shipped code and data: ``MSFLOW_WORKER_CACHE``, else the Dask worker's own local
    directory (removed with the worker), else a folder of this user's in the temporary directory."""
    configured = os.environ.get("MSFLOW_WORKER_CACHE")
    if configured:
        return Path(configured)
    try:
        from distributed import get_worker

        return Path(get_worker().local_directory) / "msflow"
    except (ImportError, ValueError):
        return Path(tempfile.gettempdir()) / f"msflow-worker-{os.getuid()}"


def worker_name() -> str:
    """This worker: a Dask worker's address, else ``<host> pid <pid>``."""
    if "distributed" in sys.modules:  # a Dask worker has imported it; a local run must not pay its import (0.4 s)
        from distributed import get_worker

        with contextlib.suppress(ValueError):  # distributed is loaded, but this is no worker's thread
            return str(get_worker().address)
    import socket

    return f"{socket.gethostname()} pid {os.getpid()}"


_VERSIONS: dict[str, str] = {}  #: import name -> "dist==version" in this worker process
_DIST_MEMO: dict[str, Any] = {}  #: distribution_versions' memo in this worker process
_CHECKED_CODE: set[tuple[str, str]] = set()
#: code tree digest -> its CodeIndex: a tree is immutable (named by its content), so its modules' fingerprints are
#: parsed once per worker process, not once per job
_INDEXES: dict[str, CodeIndex] = {}
#: code tree digest -> its record of module fingerprints (read with the tree in this process)
_TREE_MODULES: dict[str, dict[str, str]] = {}


def check_store(job: Job) -> None:
    """A store folder must exist here too: a project's ``.msflow`` is on the machine that started the run."""
    location = job.store[len("file://") :] if job.store.startswith("file://") else job.store
    if "://" in location:
        return
    if not os.path.isdir(location) or not os.access(location, os.W_OK | os.X_OK):
        raise UserError(
            f"worker {worker_name()} cannot use the store folder {location} (missing or not writable there): with "
            "--scheduler, use a store every machine reaches (s3://..., or a folder on a file system mounted at the "
            "same path everywhere)",
            stage=job.stage,
            field="store",
        )


def check_environment(job: Job) -> None:
    """Refuse a job whose key was made for another environment: key scheme, Python version, distributions."""
    from msflow.fingerprint import WORKER_PROCESS, distribution_versions
    from msflow.plan import PYTHON
    from msflow.version import KEY_SCHEME

    parts = job.key_parts or {}
    code = parts.get("code") or {}
    problems = []
    if parts.get("scheme") != KEY_SCHEME:
        problems.append(f"msflow key scheme {KEY_SCHEME} here, {parts.get('scheme')} in the key (update msflow)")
    if code.get("python") != PYTHON:
        problems.append(f"Python {PYTHON} here, {code.get('python')} in the key")
    wanted: dict[str, str] = code.get("dists") or {}
    missing = sorted(set(wanted) - set(_VERSIONS))
    if missing:  # once per name and process: a process keeps the packages it imported, whatever pip does later
        _VERSIONS.update(distribution_versions(missing, _DIST_MEMO, signature=WORKER_PROCESS))
    here = {name: _VERSIONS[name] for name in wanted}
    problems += [
        f"'{name}': {here[name]} here, {want} in the key" for name, want in wanted.items() if here[name] != want
    ]
    if problems:
        raise UserError(
            f"worker {worker_name()} refuses the job: its Python environment differs from the one the cache key "
            f"was computed in ({'; '.join(problems)}). Install the same versions on the workers",
            stage=job.stage,
            field="uses",
        )


def shipped_code(job: Job) -> Path:
    """The folder to import a shipped job's stage from: the code tree rebuilt in the worker's cache, its stage's
    import closure checked against the key's fingerprint (once per process)."""
    assert job.code is not None
    from msflow.plan import ensure_importable

    cache = worker_cache()
    root = materialise_code(job.code, open_blobs(job.store, job.store_options), cache / "code")
    for entry in list(sys.path):  # code trees of earlier runs: their modules must not resolve any more
        if entry.startswith(str(cache / "code") + "/") and entry != str(root):
            sys.path.remove(entry)
    ensure_importable(root)
    check_fingerprint(job, root)
    return root


def materialise_code(digest: str, blobs: Blobs, folder: Path) -> Path:
    """The code tree ``digest`` as files under ``folder/digest`` (built once, atomically); its document (its
    record of module fingerprints) read once per process."""
    target = folder / digest
    if target.is_dir() and digest in _TREE_MODULES:
        return target
    document = json.loads(fetch_verified(blobs, [digest])[digest])
    _TREE_MODULES[digest] = document.get("modules") or {}
    if target.is_dir():
        return target
    files: dict[str, str] = document["code"]
    pack = document.get("pack") or {"files": []}
    packed = set(pack["files"])
    contents = fetch_verified(
        blobs, [d for rel, d in files.items() if rel not in packed] + ([pack["blob"]] if packed else [])
    )
    contents.update(unpack(contents.pop(pack["blob"]), pack["files"], files) if packed else {})
    write_tree(target, {rel: contents[d] for rel, d in files.items()})
    return target


def unpack(data: bytes, packed: list[str], files: dict[str, str]) -> dict[str, bytes]:
    """The modules ``packed`` in a code tree's pack, each checked against the hash the tree gives it; returns
    content hash -> bytes."""
    from msflow.stores.packs import Pack

    out: dict[str, bytes] = {}
    try:
        pack = Pack(data, "the code pack")
        for rel in packed:
            member = pack.get(rel)
            if member is None or bytes_hash(member) != files.get(rel):
                raise UserError(f"the code pack in the store does not hold {rel} as its tree says (corrupt)")
            out[files[rel]] = member
    except ValueError as exc:
        raise UserError(f"the code pack in the store is unreadable: {exc}") from None
    return out


def write_tree(target: Path, files: dict[str, bytes]) -> None:
    """Write files into a fresh sibling folder, then rename it to ``target`` (a concurrent writer's stays)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.{uuid.uuid4().hex[:8]}.tmp"
    try:
        for rel, data in files.items():
            path = tmp / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        try:
            os.rename(tmp, target)
        except OSError:
            if not target.exists():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def check_fingerprint(job: Job, root: Path) -> None:
    """The shipped stage's import closure must fingerprint as the key says (else the code changed meanwhile).
    The tree's own record of its modules' fingerprints (``CodeTree.modules``, checked by the client against the
    keys when it made the tree; the tree's blobs are checked by content) answers without parsing; a tree without
    one is parsed here."""
    if (job.code or "", job.uses) in _CHECKED_CODE:
        return
    wanted = ((job.key_parts or {}).get("code") or {}).get("modules")
    recorded = _TREE_MODULES.get(job.code or "")
    if recorded and wanted is not None:
        found = {rel: recorded.get(rel, "missing from the shipped tree") for rel in wanted}
    else:
        found = parsed_closure(job, root)
    if wanted is not None and found != wanted:
        changed = sorted(set(found.items()) ^ set(wanted.items()))
        raise UserError(
            f"the shipped code does not match the cache key's fingerprint ({', '.join(sorted({r for r, _ in changed}))} "
            "differ): was the code edited during the run? Run again",
            stage=job.stage,
            field="uses",
        )
    _CHECKED_CODE.add((job.code or "", job.uses))


def parsed_closure(job: Job, root: Path) -> dict[str, str]:
    """The stage's import closure fingerprinted from the shipped files (one CodeIndex per tree and process)."""
    from msflow.fingerprint import CodeIndex

    index = _INDEXES.get(job.code or "")
    if index is None or index.root != root.resolve():
        index = _INDEXES[job.code or ""] = CodeIndex(root)
    modules: dict[str, str] = index.closure(job.uses.partition(":")[0])["modules"]
    return modules


def shipped_files(entry: JobInput, job: Job) -> Files:
    """A shipped data-files input: each blob rebuilt under the worker's cache with its original file name."""
    from msflow.stage import Files

    assert entry.blobs is not None
    blobs = open_blobs(job.store, job.store_options)
    folder = worker_cache() / "files"
    paths = {
        label: materialise_file(entry.blobs[label], name, label in entry.folders, blobs, folder)
        for label, name in entry.files
    }
    return Files(paths, entry.fields)


def materialise_file(digest: str, name: str, is_folder: bool, blobs: Blobs, folder: Path) -> Path:
    """``folder/digest/name``: a file's bytes, or a folder tree's files (built once, atomically)."""
    target = folder / digest / name
    if target.exists():
        return target
    data = fetch_verified(blobs, [digest])[digest]
    if not is_folder:
        write_file(target, data)
        return target
    entries: dict[str, str] = json.loads(data)["folder"]
    contents = fetch_verified(blobs, list(entries.values()))
    write_tree(target, {rel: contents[d] for rel, d in entries.items()})
    return target


def write_file(target: Path, data: bytes) -> None:
    from msflow.atomic import write_atomic

    target.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(target, data)
