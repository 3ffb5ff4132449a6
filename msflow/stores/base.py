"""The store contract: what the runner, workers and commands need from a place that keeps artifacts and records.

Two backends implement it: ``LocalStore`` (a folder on a local or shared POSIX file system) and ``RemoteStore``
(an object store: ``s3://``, any fsspec URL). Code that uses a store is typed against ``Store`` and never probes
for optional methods: every backend implements every method.

Artifacts are immutable once published and addressed by their cache key. Writing goes through an
``ArtifactWriter``: output sinks ``put`` chunks into it while a stage runs, ``commit`` publishes atomically, and
leaving its ``with`` block without a commit removes what was written.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Iterator, Mapping
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from pathlib import Path

    from msflow.artifact import ArtifactView

HOST = socket.gethostname()

Json = dict[str, Any]


class ArtifactWriter(Protocol):
    """One artifact being written under a key (a private folder until committed)."""

    def __enter__(self) -> ArtifactWriter: ...

    def __exit__(self, *exc: object) -> None: ...

    def put(self, rel: str, data: bytes) -> None:
        """Write one file of the artifact's zarr group now (e.g. a chunk of an output sink)."""
        ...

    def commit(
        self,
        arrays: Mapping[str, Any],
        extra: Json,
        file_suffixes: Mapping[str, str | None] | None = None,
        replace: bool = False,
    ) -> Json:
        """Write the remaining arrays and the manifest, publish atomically; return the committed manifest."""
        ...

    def abort(self) -> None:
        """Remove whatever was written (nothing once committed)."""
        ...


class Store(Protocol):
    """Artifacts by cache key, per-key locks, the machine's memo, and run and sweep records."""

    url: str  #: what a worker needs to reopen the store, with ``options``
    options: Json
    #: ``has`` asks a server (a round trip): the runner then leaves the check of a stage whose input was just
    #: computed to the worker's check under the key's lock, which it makes anyway
    remote: bool
    #: this machine's folder for the store's caches (the memo; tools' caches such as matplotlib's); None: none
    local_cache: Path | None

    # artifacts
    def has(self, key: str) -> bool: ...
    def manifest(self, key: str) -> Json: ...
    def open(self, key: str) -> ArtifactView: ...
    def keys(self) -> Iterator[str]: ...
    def writer(self, key: str) -> ArtifactWriter: ...
    def write(
        self,
        key: str,
        arrays: Mapping[str, Any],
        extra: Json,
        file_suffixes: Mapping[str, str | None] | None = None,
        replace: bool = False,
    ) -> Json: ...
    def verify(self, key: str) -> list[str]: ...
    def size(self, key: str) -> int: ...
    def remove(self, key: str) -> None: ...
    def quarantine(self, key: str, reason: str) -> str: ...
    def drop_quarantined(self, *, dry_run: bool = False) -> tuple[list[str], int]: ...
    def clean_tmp(self, *, max_age: float | None = None) -> list[str]: ...

    # coordination
    def lock(self, key: str, on_wait: Callable[[Json], None] | None = None) -> AbstractContextManager[object]: ...
    def computing(self, key: str) -> Json | None:
        """Who holds ``key``'s lock now, computing it (host, pid, since; {} when unreadable), or None."""

    def in_use(
        self, *, alone: bool = False, on_wait: Callable[[Json], None] | None = None
    ) -> AbstractContextManager[object]:
        """Held by every run while it makes and records artifacts (any number at once); ``alone`` (gc): held by
        nobody else, else ``StoreInUse`` at once. A run that finds gc holding it waits for gc to end, calling
        ``on_wait`` (with what is known of gc: host, pid) first."""

    # memo and records
    def load_memo(self) -> Json: ...
    def save_memo(self, memo: Json) -> None: ...
    def write_run(self, record: Json) -> str: ...
    def run_ids(self) -> list[str]: ...
    def read_run(self, run_id: str) -> Json: ...
    def remove_run(self, run_id: str) -> None: ...
    def write_sweep(self, record: Json) -> str: ...
    def sweep_ids(self) -> list[str]: ...
    def read_sweep(self, sweep_id: str) -> Json: ...


def env_megabytes(variable: str, default: float) -> int:
    """A size in bytes from an environment variable in megabytes (``default`` when unset or not a number)."""
    try:
        megabytes = float(os.environ.get(variable, default))
    except ValueError:
        megabytes = default
    return max(0, int(megabytes * 1e6))


#: set by a run for the processes it starts (pool workers, a local Dask cluster): the pid a user knows it by
RUN_PID_VARIABLE = "MSFLOW_RUN_PID"


def holder_fields() -> Json:
    """Who holds a lock or lease: host and pid (the process that took it: its liveness decides staleness) and, in
    a run's worker process, ``run_pid``, the ``msflow run`` process the user sees."""
    fields: Json = {"host": HOST, "pid": os.getpid()}
    run = os.environ.get(RUN_PID_VARIABLE, "")
    if run.isdigit() and int(run) != os.getpid():
        fields["run_pid"] = int(run)
    return fields


def describe_holder(holder: Json) -> str:
    """``pid 12 on host`` (the run's pid, and its worker's when another process holds it)."""
    run, pid = holder.get("run_pid"), holder.get("pid", "?")
    worker = f", in its worker {pid}" if run is not None else ""
    return f"pid {run if run is not None else pid} on {holder.get('host', '?')}{worker}"


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (a process of another user counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def json_object(data: bytes | str) -> Json:
    """Parse a JSON object (a record, a manifest, a memo); ValueError when it is not one."""
    import json

    value = json.loads(data)
    if not isinstance(value, dict):
        raise ValueError(f"expected a JSON object, got {type(value).__name__}")
    return value


def record_object(data: bytes, location: str) -> Json:
    """A stored run or sweep record (at ``location``, for messages); CorruptRecord when it is not a JSON object
    (damaged on disk or edited by hand): said plainly, never half-read."""
    from msflow.errors import CorruptRecord

    try:
        return json_object(data)
    except ValueError as exc:
        raise CorruptRecord(None, f"the record {location} is unreadable ({exc})") from None


def run_record(data: bytes, location: str, read_raw: Callable[[str], Json]) -> Json:
    """A stored run record as readers use it (``record_object``, then ``expand_record``)."""
    return expand_record(record_object(data, location), read_raw)


def expand_record(record: Json, read_raw: Callable[[str], Json]) -> Json:
    """A run record as readers use it: a small no-op record (``same_as``) merged into the full record it points
    at, every stage cached. A record whose full record is gone stays small (with ``missing_full_record``)."""
    target = record.get("same_as")
    if not isinstance(target, str):
        return record
    try:
        full = read_raw(target)
    except (OSError, ValueError, KeyError):
        return {**record, "missing_full_record": True, "stages": {}, "config": {}}
    stages = {n: {**e, "state": "cached", "detail": None, "seconds": 0.0} for n, e in full.get("stages", {}).items()}
    return {**full, **record, "stages": stages}


def matching_run(run_id: str, run_ids: list[str], location: str) -> str:
    """The one run whose id starts or ends with ``run_id`` (a prefix or the random suffix); a UserError naming
    what to do when none or several do."""
    matches = [r for r in run_ids if r.startswith(run_id) or r.endswith(run_id)]
    if len(matches) == 1:
        return matches[0]
    from msflow.errors import UserError

    if not matches:
        raise UserError(f"no run matches '{run_id}'; `msflow runs` lists them", file=location)
    shown = ", ".join(matches[:4]) + (", ..." if len(matches) > 4 else "")
    raise UserError(f"'{run_id}' matches {len(matches)} runs ({shown}): give more of the id", file=location)


def new_run_id() -> str:
    """A run (or sweep) id, sortable by start time to the microsecond (records of one second still order)."""
    import uuid
    from datetime import UTC, datetime

    return datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%f") + "-" + uuid.uuid4().hex[:6]
