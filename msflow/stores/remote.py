"""The artifact store on an object store (``s3://bucket/prefix`` or any fsspec URL), same interface as LocalStore.

Layout under the store's prefix::

    commits/<k[:2]>/<key>.json       commit marker: names the key's data folder and holds its manifest
    artifacts/<k[:2]>/<key>/<wid>/   zarr v3 groups, one folder per writer (wid: time, random); a small artifact's
                                     group is one object there, artifact.zip (msflow.stores.packs)
    pending/<key>.<wid>.json         journal of folders that may become garbage (being written or retired)
    locks/<key>.lease                per-key leases (msflow.stores.leases)
    active/<token>.lease             one per run in progress, renewed like a lease: gc refuses while any is live
    runs/<id>.json                   one record per run (shared by every machine using the store)
    sweeps/<id>.json                 one record per sweep

The memo of file stat signatures and code fingerprints is machine-local: it lives in the pipeline's local cache
(``.msflow/cache``), never in the store.

Atomic publish
    A writer journals its folder (the PUT overlapping the re-check under the lease), uploads the zarr group into
    it, then writes the commit marker: one small object, created conditionally (``If-None-Match: *``) so the
    first committed artifact of a key stays. Readers
    (has, manifest, open, keys, verify) look at commit markers only, so a folder without one - a writer killed
    mid-upload - is invisible. ``replace=True`` (``msflow run --force``) journals the old folder, overwrites the
    marker in one PUT (readers see the old artifact or the new one, never a mix); the old folder stays for
    RETIRE_SECONDS, so a reader that read the old marker can finish. Removal deletes the marker first. Under a
    lease the journal of the committed folder is deleted together with the lease's release (one round trip),
    which is sent in the background (settled at the end of the run and at process exit).
Cleanup
    clean_tmp reads the journal (small: only unfinished work is in it). A folder being written is deleted once
    its writer is gone - a dead process on this host, or for another host no live lease on the key and older
    than ``max_age`` (default an hour) - unless the marker names it (killed between commit and journal
    cleanup). A retired folder is deleted RETIRE_SECONDS (or ``max_age``) after its replacement. Leases of
    dead holders are deleted too. Every run that computes something and ``msflow gc`` call it. The presences of
    killed runs (``active/``, see ``in_use``) are deleted by ``msflow gc``.
Locks (the rule)
    Any number of runs, on any number of machines, may share a store. Each key has a lease (60 s, or
    MSFLOW_LEASE_SECONDS) renewed by a heartbeat while its stage runs; a lease is broken when it expired or when
    its holder ran on this host and is dead (see msflow.stores.leases). So each stage instance is computed
    once; a holder stalled past its ttl may see its work duplicated, never a torn or mixed artifact, because
    the commit is conditional. On S3 expiry is judged by the server's clock; on other fsspec backends by the
    machines' clocks (keep them within a second or two).
Errors
    The first opening in a process makes one cheap request (bounded by MSFLOW_STORE_TIMEOUT, 15 s), so a
    missing bucket, missing credentials or an unreachable endpoint stop the run at once with a UserError that
    names the store URL.
No-op path
    ``has`` is one GET of the commit marker, and the manifest comes with it: a cached stage costs one small
    request. Opening an artifact reads no metadata beyond the marker; outputs are fetched chunk by chunk in
    parallel, or through zarr for lazy access. A stage whose input the run just computed is not checked by the
    run (``remote``; msflow.runner.Runner.needs_check): the check under its lease is the only one.
Reading what this process just wrote
    Markers and data objects this process wrote or read lately are answered from memory (msflow.stores.recent):
    the next stage of a chain run by the same process fetches nothing of its input. ``has`` and ``verify``
    always ask the server.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, wait
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from msflow.artifact import check_manifest
from msflow.atomic import write_json_atomic
from msflow.errors import CorruptArtifact, StoreInUse, UserError
from msflow.stored import StoredArray
from msflow.stores.base import (
    HOST,
    Json,
    describe_holder,
    json_object,
    matching_run,
    pid_alive,
    record_object,
    run_record,
)
from msflow.stores.leases import GC_PREFIX, Lease, Presence, lease_is_stale, live_presences, parse_holder
from msflow.stores.objects import dumps, iter_chunks, make_objects
from msflow.stores.packs import PACK_NAME, Pack, make_pack, pack_limit, take_small
from msflow.stores.recent import RecentObjects, caches_for

if TYPE_CHECKING:
    from msflow.artifact import ArtifactView

MARKER_FORMAT = 1
STALE_SECONDS = 3600.0  # a journalled folder of a writer on another host, without a live lease, is gone after this
SETTLE_SECONDS = 30.0  # the longest a run waits at its end for its lease releases to land
RETIRE_SECONDS = 60.0  # a folder replaced by --force stays readable this long for readers that opened it

_PROBED: set[str] = set()
T = TypeVar("T")


def open_remote_store(url: str, options: dict[str, Any] | None, cache_dir: str | Path | None = None) -> RemoteStore:
    """A RemoteStore for ``url``; the first opening in a process checks bucket, credentials and endpoint."""
    store = RemoteStore(url, options or {}, cache_dir)
    probe_key = json.dumps([url, options or {}], sort_keys=True, default=str)
    if probe_key not in _PROBED:
        store.objects.probe()
        _PROBED.add(probe_key)
    return store


def writer_id() -> str:
    """Unique and sortable by creation time."""
    return f"{time.time_ns() // 1000:x}-{uuid.uuid4().hex[:10]}"


class RemoteStore:
    remote = True  # has() is a request

    def __init__(self, url: str, options: dict[str, Any], cache_dir: str | Path | None = None):
        protocol, sep, path = url.partition("://")
        self.url = protocol + sep + path.rstrip("/")
        self.options = dict(options)
        self.local_cache = Path(cache_dir) if cache_dir is not None else None
        self.objects = make_objects(self.url, self.options)
        self._recent: dict[str, Json] = {}  # markers read by has(), consumed by the manifest() that follows
        self._caches = caches_for(self.url)  # what this process wrote or read lately (msflow.stores.recent)
        self._held: dict[str, list[str]] = {}  # key under our lease -> journals to delete when it is released

    # ------------------------------------------------------------------ paths
    @staticmethod
    def marker_path(key: str) -> str:
        return f"commits/{key[:2]}/{key}.json"

    @staticmethod
    def data_path(key: str, wid: str) -> str:
        return f"artifacts/{key[:2]}/{key}/{wid}"

    @staticmethod
    def journal_path(key: str, wid: str) -> str:
        return f"pending/{key}.{wid}.json"

    # ------------------------------------------------------------------ reading
    def _marker(self, key: str) -> Json | None:
        """The key's valid commit marker, or None (absent or unreadable)."""
        data = self.objects.get(self.marker_path(key))
        return None if data is None else parse_marker(key, data)

    def has(self, key: str) -> bool:
        """Whether a commit marker exists for ``key`` (an unreadable one counts: reading it raises CorruptArtifact)."""
        data = self.objects.get(self.marker_path(key))
        if data is None:
            self._recent.pop(key, None)
            return False
        marker = parse_marker(key, data)
        self._recent[key] = marker or {"corrupt": "its commit marker is unreadable"}
        self._remember(key, marker)
        return True

    def _committed(self, key: str) -> Json:
        marker = self._recent.pop(key, None)
        if marker is None and self._caches.enabled:
            marker = self._caches.markers.get(key)
        if marker is None:
            data = self.objects.get(self.marker_path(key))
            if data is None:
                raise FileNotFoundError(f"no artifact {key} in {self.url}")
            marker = parse_marker(key, data)
            self._remember(key, marker)
            marker = marker or {"corrupt": "its commit marker is unreadable"}
        if "corrupt" in marker:
            raise CorruptArtifact(key, marker["corrupt"])
        return marker

    def _remember(self, key: str, marker: Json | None) -> None:
        """Keep a valid marker this process wrote or read for the next reader of the key (msflow.stores.recent)."""
        if marker is not None and self._caches.enabled:
            self._caches.markers.put(key, marker)

    def _forget(self, key: str) -> None:
        self._recent.pop(key, None)
        self._caches.markers.forget(key)

    def manifest(self, key: str) -> dict[str, Any]:
        manifest: Json = self._committed(key)["manifest"]
        return manifest

    def open(self, key: str) -> ArtifactView:
        return self._view(key, self._committed(key))

    def _pack_source(self, key: str, marker: Json, recent: RecentObjects | None) -> PackSource | None:
        """The artifact's pack, when ``marker`` says its group is one (msflow.stores.packs); fetched on first use."""
        if not marker.get("pack"):
            return None
        return PackSource(self, f"{self.data_path(key, marker['data'])}/{marker['pack']}", recent)

    def _view(self, key: str, marker: Json, cached: bool = True, pack: PackSource | None = None) -> ArtifactView:
        """The artifact ``marker`` names; ``cached``: chunks this process holds are not fetched again; ``pack``:
        its pack source when the caller has one already (else made here)."""
        from msflow.artifact import ArtifactView

        manifest = marker["manifest"]
        folder = self.data_path(key, marker["data"])
        chunks = marker.get("chunks", {})
        recent = self._caches.objects if cached else None
        checksum = manifest.get("format", 1) >= 2
        pack = pack or self._pack_source(key, marker, recent)
        arrays = {
            name: RemoteArray(self, folder, name, entry, chunks.get(name), checksum=checksum, recent=recent, pack=pack)
            for name, entry in manifest["outputs"].items()
        }
        return ArtifactView(arrays, manifest.get("meta", {}), manifest.get("metrics", {}), key=key, manifest=manifest)

    def keys(self) -> Iterator[str]:
        for info in self.objects.list("commits/"):
            name = info.path.rsplit("/", 1)[-1]
            if name.endswith(".json"):
                yield name[: -len(".json")]

    def verify(self, key: str) -> list[str]:
        from msflow.artifact import check_contents

        raw = self.objects.get(self.marker_path(key))
        if raw is None:
            return ["no commit marker (not published)"]
        try:
            marker = json.loads(raw)
            folder = self.data_path(key, marker["data"])
            recorded = marker["manifest"]
        except (ValueError, KeyError, TypeError) as exc:
            return [f"commit marker unreadable: {type(exc).__name__}: {exc}"]
        problems = []
        pack = self._pack_source(key, marker, None)  # fetched once, for the group's zarr.json and every output
        try:
            group = pack.load().get("zarr.json") if pack else self.objects.get(f"{folder}/zarr.json")
        except (ValueError, FileNotFoundError) as exc:
            return [f"the artifact's pack is unreadable: {exc}"]
        if group is None:
            problems.append(f"zarr.json missing under {folder}")
        else:
            try:
                stored = json.loads(group)["attributes"]["msflow"]
            except (ValueError, KeyError, TypeError) as exc:
                problems.append(f"zarr.json unreadable: {type(exc).__name__}: {exc}")
            else:
                if stored != recorded:
                    problems.append("zarr.json manifest differs from the commit marker's")
        return problems + check_contents(recorded, self._view(key, marker, cached=False, pack=pack).__getitem__)

    def size(self, key: str) -> int:
        marker = self._marker(key)
        if marker is None:
            return 0
        return sum(o.size for o in self.objects.list(self.data_path(key, marker["data"]) + "/"))

    # ------------------------------------------------------------------ writing
    def writer(self, key: str) -> RemoteWriter:
        """An artifact being written under ``key`` into a fresh folder; ``commit`` writes the marker."""
        return RemoteWriter(self, key)

    def write(
        self,
        key: str,
        arrays: Mapping[str, Any],
        extra: Json,
        file_suffixes: Mapping[str, str | None] | None = None,
        replace: bool = False,
    ) -> Json:
        """Upload the zarr group under a fresh folder, then commit it with the marker; returns the manifest."""
        with self.writer(key) as writer:
            return writer.commit(arrays, extra, file_suffixes, replace)

    def commit_folder(
        self, key: str, wid: str, manifest: dict[str, Any], replace: bool, packed: bool = False
    ) -> dict[str, Any]:
        """Write the commit marker naming folder ``wid`` (``packed``: its group is one zip, PACK_NAME); returns
        the manifest that is committed (another writer's, if one won the race)."""
        from msflow.chunks import array_metadata

        chunks = {
            name: array_metadata(tuple(entry["shape"]), entry["dtype"])["chunk_grid"]["configuration"]["chunk_shape"]
            for name, entry in manifest["outputs"].items()
        }
        committed = dumps(
            {
                "format": MARKER_FORMAT,
                "key": key,
                "data": wid,
                "manifest": manifest,
                "chunks": chunks,
                **({"pack": PACK_NAME} if packed else {}),
                "host": HOST,
                "pid": os.getpid(),
                "committed": time.time(),
            }
        )
        marker = parse_marker(key, committed)
        if replace:
            self._replace(key, wid, committed)
        elif self.objects.create(self.marker_path(key), committed) is None:
            # published meanwhile by another writer of the key: theirs stays
            self.objects.delete_prefix(self.data_path(key, wid) + "/")
            marker = self._marker(key)
            manifest = (marker or {}).get("manifest", manifest)
        self._forget(key)
        self._remember(key, marker)
        return manifest

    def _replace(self, key: str, wid: str, marker: bytes) -> None:
        """Overwrite the marker; the old folder is retired, not deleted, so a reader that read the old marker
        a moment ago can still read its chunks. clean_tmp deletes it RETIRE_SECONDS later."""
        old = self._marker(key)
        if old and old["data"] != wid:
            self.objects.put(self.journal_path(key, old["data"]), self.journal_entry(key, old["data"], "retire"))
        self.objects.put(self.marker_path(key), marker)

    def abandon(self, key: str, wid: str) -> None:
        """Best effort after a failed write: delete our folder unless the marker names it (a commit whose
        response was lost); whatever this cannot do, clean_tmp does later from the journal."""
        with contextlib.suppress(Exception):
            marker = self._marker(key)
            if marker is None or marker.get("data") != wid:
                self.objects.delete_prefix(self.data_path(key, wid) + "/")
            self.objects.delete(self.journal_path(key, wid))

    @staticmethod
    def journal_entry(key: str, wid: str, action: str) -> bytes:
        return dumps(
            {"key": key, "data": wid, "action": action, "host": HOST, "pid": os.getpid(), "started": time.time()}
        )

    def quarantine(self, key: str, reason: str) -> str:
        """Move a corrupt artifact aside: its marker goes to corrupt/ with the reason (the data folder it names
        stays for inspection); the key becomes free to recompute. Returns where it went."""
        data = self.objects.get(self.marker_path(key))
        self._forget(key)
        if data is None:
            return ""
        path = f"corrupt/{key}.{writer_id()}.json"
        self.objects.put(path, dumps({"key": key, "reason": reason, "marker": data.decode("utf-8", "replace")}))
        self.objects.delete(self.marker_path(key))
        return f"{self.url}/{path}"

    def drop_quarantined(self, *, dry_run: bool = False) -> tuple[list[str], int]:
        """Delete the artifacts ``quarantine`` set aside (the record in corrupt/ and the data folder it names);
        returns their names and bytes."""
        names, freed = [], 0
        for info in self.objects.list("corrupt/"):
            folder = self._quarantined_folder(info.path)
            data = list(self.objects.list(folder)) if folder else []
            names.append(info.path.removeprefix("corrupt/").removesuffix(".json"))
            freed += info.size + sum(o.size for o in data)
            if not dry_run:
                if folder:
                    self.objects.delete_prefix(folder)
                self.objects.delete(info.path)
        return names, freed

    def _quarantined_folder(self, path: str) -> str:
        """The data folder (``.../``) a record in corrupt/ names, or "" when it names none that can be read."""
        try:
            record = json.loads(self.objects.get(path) or b"")
            marker = json.loads(record["marker"])
            return self.data_path(record["key"], marker["data"]) + "/"
        except (ValueError, KeyError, TypeError):
            return ""

    def remove(self, key: str) -> None:
        marker = self._marker(key)
        if marker is None:
            return
        wid = marker["data"]
        self.objects.put(self.journal_path(key, wid), self.journal_entry(key, wid, "retire"))
        self.objects.delete(self.marker_path(key))
        self._forget(key)
        self.objects.delete_prefix(self.data_path(key, wid) + "/")
        self.objects.delete(self.journal_path(key, wid))

    def clean_tmp(self, *, max_age: float | None = None) -> list[str]:
        """Delete folders of writers that are gone and folders retired by replace (see the module docstring),
        and leases of dead holders; returns the deleted folders as ``<key>.<wid>``."""
        removed = []
        for info in self.objects.list("pending/"):
            raw = self.objects.get(info.path)
            if raw is None:
                continue  # finished meanwhile
            try:
                entry = json.loads(raw)
                key, wid = entry["key"], entry["data"]
            except (ValueError, KeyError, TypeError):
                self.objects.delete(info.path)
                continue
            if entry.get("action") == "retire":
                keep = _age(entry) < (RETIRE_SECONDS if max_age is None else max_age)
            else:
                keep = self._writer_alive(entry, STALE_SECONDS if max_age is None else max_age)
            if keep:
                continue
            marker = self._marker(key)
            if marker is None or marker.get("data") != wid:
                self.objects.delete_prefix(self.data_path(key, wid) + "/")
                removed.append(f"{key}.{wid}")
            self.objects.delete(info.path)
        for info in self.objects.list("locks/"):
            current = self.objects.get_versioned(info.path)
            if current is not None and lease_is_stale(parse_holder(current.data), current.age):
                self.objects.delete_if(info.path, current.etag)
        return removed

    def _writer_alive(self, entry: dict[str, Any], grace: float) -> bool:
        pid = entry.get("pid")
        if entry.get("host") == HOST and isinstance(pid, int):
            return pid_alive(pid)
        lease = self.objects.get_versioned(self.lease_path(entry["key"]))
        if lease is not None and not lease_is_stale(parse_holder(lease.data), lease.age):
            return True
        return _age(entry) < grace

    def computing(self, key: str) -> Json | None:
        """The holder of the key's live lease (a run computing it now), or None (one GET)."""
        current = self.objects.get_versioned(self.lease_path(key))
        if current is None:
            return None
        holder = parse_holder(current.data)
        return None if lease_is_stale(holder, current.age) else holder

    @contextlib.contextmanager
    def in_use(self, *, alone: bool = False, on_wait: Callable[[Json], None] | None = None) -> Iterator[None]:
        """A run is present on the store while it runs (``active/<token>.lease``, renewed by a heartbeat:
        msflow.stores.leases.Presence), on whichever machine; gc (``alone``) fails while any live one is there.
        gc is present too (``gc/``), written before it lists the runs, and a run that finds it after writing
        its own waits for it to end (``on_wait`` told once): of a run and a gc starting together, one always
        sees the other."""
        if not alone:
            with Presence(self.objects):
                self._await_gc(on_wait)
                yield
            return
        with Presence(self.objects, prefix=GC_PREFIX):
            runs = live_presences(self.objects)
            if runs:
                where = ", ".join(describe_holder(r) for r in runs[:3])
                raise StoreInUse(
                    f"{len(runs)} run(s) are using the store {self.url} ({where}): gc would delete the artifacts "
                    "they are making before their records name them; run gc once they have ended"
                )
            yield

    def _await_gc(self, on_wait: Callable[[Json], None] | None, poll: float = 0.2) -> None:
        """Return once no gc is present on the store (a killed gc's presence goes stale)."""
        told = False
        while gcs := live_presences(self.objects, GC_PREFIX):
            if on_wait is not None and not told:
                on_wait(gcs[0])
                told = True
            time.sleep(poll)  # an object store notifies nobody: poll, as a key's lock does

    # ------------------------------------------------------------------ locks
    @staticmethod
    def lease_path(key: str) -> str:
        return f"locks/{key}.lease"

    @contextlib.contextmanager
    def lock(self, key: str, on_wait: Callable[[Json], None] | None = None, poll: float = 0.1) -> Iterator[Lease]:
        """Exclusive per-key lease across processes and machines (msflow.stores.leases). The release is sent when
        the block ends and not waited for (``settle_releases``), so its round trip overlaps what comes next."""
        name = f"{self.url}/{self.lease_path(key)}"
        _await_release(name)  # this process's own release of the key, still in flight: let it land first
        lease = Lease(self.objects, self.lease_path(key))
        lease.acquire(on_wait, poll)
        self._held[key] = []
        try:
            yield lease
        finally:
            _release_soon(name, in_background(self._release, lease, self._held.pop(key, [])))

    def _release(self, lease: Lease, journals: list[str]) -> None:
        """Release the lease and, at the same time, delete the journals of folders committed under it: one round
        trip instead of two. A journal left behind (a failed delete, a kill) names a committed folder, which
        clean_tmp keeps while it deletes the journal."""
        if not journals:
            lease.release()
            return
        deleter = threading.Thread(target=self._delete_quietly, args=(journals,), name="msflow-journal-delete")
        deleter.start()
        try:
            lease.release()
        finally:
            deleter.join()

    def _delete_quietly(self, paths: list[str]) -> None:
        for path in paths:
            with contextlib.suppress(Exception):
                self.objects.delete(path)

    # ------------------------------------------------------------------ memo, runs
    def load_memo(self) -> dict[str, Any]:
        if self.local_cache is None:
            return {}
        try:
            return json_object((self.local_cache / "memo.json").read_bytes())
        except (OSError, ValueError):
            return {}

    def save_memo(self, memo: dict[str, Any]) -> None:
        if self.local_cache is None:
            return
        self.local_cache.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.local_cache / "memo.json", memo)

    def _write_record(self, folder: str, record: dict[str, Any]) -> str:
        path = f"{folder}/{record['id']}.json"
        self.objects.put(path, json.dumps(record, indent=1, sort_keys=True, allow_nan=False).encode())
        return f"{self.url}/{path}"

    def _record_ids(self, folder: str) -> list[str]:
        names = (info.path.rsplit("/", 1)[-1] for info in self.objects.list(f"{folder}/"))
        return sorted(n[: -len(".json")] for n in names if n.endswith(".json"))

    def write_run(self, record: dict[str, Any]) -> str:
        return self._write_record("runs", record)

    def run_ids(self) -> list[str]:
        return self._record_ids("runs")

    def read_run(self, run_id: str) -> dict[str, Any]:
        data = self.objects.get(f"runs/{run_id}.json")
        if data is None:
            run_id = matching_run(run_id, self.run_ids(), self.url)
            data = self.objects.get(f"runs/{run_id}.json")
            if data is None:
                raise UserError(f"run '{run_id}' vanished from {self.url}", file=self.url)
        return run_record(data, f"{self.url}/runs/{run_id}.json", self._read_raw_run)

    def _read_raw_run(self, run_id: str) -> Json:
        data = self.objects.get(f"runs/{run_id}.json")
        if data is None:
            raise FileNotFoundError(f"runs/{run_id}.json")
        return json_object(data)

    def remove_run(self, run_id: str) -> None:
        self.objects.delete(f"runs/{run_id}.json")

    def write_sweep(self, record: dict[str, Any]) -> str:
        return self._write_record("sweeps", record)

    def sweep_ids(self) -> list[str]:
        return self._record_ids("sweeps")

    def read_sweep(self, sweep_id: str) -> dict[str, Any]:
        data = self.objects.get(f"sweeps/{sweep_id}.json")
        if data is None:
            raise UserError(f"no sweep '{sweep_id}'", file=self.url)
        return record_object(data, f"{self.url}/sweeps/{sweep_id}.json")


class RemoteWriter:
    """One artifact being written: objects go to a fresh folder, journalled before the first upload so clean_tmp
    can find it if the writer dies, and the commit marker written last makes it visible. The journal's PUT is
    sent when the writer is made and awaited before the first upload, so its round trip overlaps whatever the
    caller does meanwhile (under a lease: the re-check for an artifact published meanwhile, then the stage)."""

    def __init__(self, store: RemoteStore, key: str):
        self.store = store
        self.key = key
        self.wid = writer_id()
        self.folder = store.data_path(key, self.wid)
        self.journal = store.journal_path(key, self.wid)
        self._journalled = in_background(store.objects.put, self.journal, store.journal_entry(key, self.wid, "write"))
        self.uploading = False  # set before the first upload: from then on the folder may hold objects
        self.committed = False
        self.streamed = False  # objects uploaded before the commit (chunks of output sinks)
        self._for_pack: dict[str, bytes] = {}  # chunks of output sinks kept for the pack while they are small
        self._for_pack_size = 0

    def __enter__(self) -> RemoteWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.abort()

    def _start(self) -> None:
        """Wait for the journal entry (a failed PUT raises here, before anything is uploaded)."""
        self._journalled.result()
        self.uploading = True

    def put(self, rel: str, data: bytes) -> None:
        """One object of the zarr group (a chunk of an output sink): held for the commit's pack while the held
        ones add up to at most the pack limit, then uploaded with them, and every later one at once (streamed)."""
        if not self.streamed:
            self._for_pack[rel] = data
            self._for_pack_size += len(data)
            if self._for_pack_size <= pack_limit():
                return
            self.streamed = True
            kept, self._for_pack = self._for_pack, {}
            self._upload(kept)
            return
        self._upload({rel: data})

    def _upload(self, items: Mapping[str, bytes]) -> None:
        """Objects of the group (paths relative to it) into the folder, concurrently; kept for this process's
        readers, but for the arrays' zarr.json (readers take the layout from the marker)."""
        self._start()
        uploads = {f"{self.folder}/{rel}": data for rel, data in items.items()}
        self.store.objects.put_many(uploads)
        for path, data in uploads.items():
            if not path.endswith("zarr.json"):
                self.store._caches.objects.put(path, data)

    def commit(
        self,
        arrays: Mapping[str, Any],
        extra: Json,
        file_suffixes: Mapping[str, str | None] | None = None,
        replace: bool = False,
    ) -> Json:
        """Upload the remaining arrays and the group's zarr.json, then write the marker; returns the manifest."""
        from msflow.artifact import encode_artifact, prepare_manifest

        arrays, manifest = prepare_manifest(arrays, extra, file_suffixes)
        self._start()
        objects = self.store.objects
        # chunks of sinks the stage opened but did not return (the folder is this writer's own: nothing else there)
        for info in objects.list(self.folder + "/") if self.streamed else []:
            if info.path[len(self.folder) + 1 :].split("/")[0] not in arrays:
                objects.delete(info.path)
        kept = [(rel, data) for rel, data in self._for_pack.items() if rel.split("/")[0] in arrays]
        self._for_pack = {}
        encoded = itertools.chain(kept, encode_artifact(arrays, manifest))
        small, packed = take_small(encoded) if not self.streamed else ([], False)
        if packed:  # one object instead of one per array and chunk (msflow.stores.packs)
            self._upload({PACK_NAME: make_pack(small)})
        for batch in iter_chunks(itertools.chain(small, encoded)) if not packed else ():
            self._upload(batch)
        manifest = self.store.commit_folder(self.key, self.wid, manifest, replace, packed)
        self.committed = True
        under_lease = self.store._held.get(self.key)
        if under_lease is not None:
            under_lease.append(self.journal)  # deleted beside the lease's release (RemoteStore._release)
        else:
            objects.delete(self.journal)
        return manifest

    def abort(self) -> None:
        """Best effort after a failed or unneeded write (nothing once committed); clean_tmp does the rest from the
        journal. A writer that uploaded nothing only takes its journal entry back."""
        if self.committed:
            return
        if self.uploading:
            self.store.abandon(self.key, self.wid)
            return
        with contextlib.suppress(Exception):
            self._journalled.result()
            self.store.objects.delete(self.journal)


_RELEASES: dict[str, Future[None]] = {}  #: "<store url>/<lease path>" -> its release in flight, in this process
_RELEASES_LOCK = threading.Lock()


def _release_soon(name: str, release: Future[None]) -> None:
    with _RELEASES_LOCK:
        if not _RELEASES:
            _settle_at_exit()
        _RELEASES[name] = release

    def done(_: Future[None]) -> None:
        with _RELEASES_LOCK:
            if _RELEASES.get(name) is release:
                del _RELEASES[name]

    release.add_done_callback(done)


def _await_release(name: str) -> None:
    with _RELEASES_LOCK:
        release = _RELEASES.get(name)
    if release is not None:
        wait([release], timeout=SETTLE_SECONDS)


def settle_releases(timeout: float = SETTLE_SECONDS) -> None:
    """Wait until this process's lease releases in flight have landed (at the end of a run and before the
    process exits); a release that failed leaves a lease that lapses after its ttl."""
    with _RELEASES_LOCK:
        pending = list(_RELEASES.values())
    wait(pending, timeout=timeout)


_SETTLING_AT_EXIT: list[bool] = []


def _settle_at_exit() -> None:
    """Once per process: settle the releases at exit, also in multiprocessing's workers (which skip atexit)."""
    if not _SETTLING_AT_EXIT:
        from multiprocessing.util import Finalize

        Finalize(None, settle_releases, exitpriority=10)
        _SETTLING_AT_EXIT.append(True)


def in_background(fn: Callable[..., T], *args: Any) -> Future[T]:
    """Call ``fn(*args)`` in a new daemon thread; its result or exception arrives through the returned future."""
    future: Future[T] = Future()

    def call() -> None:
        try:
            future.set_result(fn(*args))
        except BaseException as exc:  # handed to whoever waits on the future
            future.set_exception(exc)

    threading.Thread(target=call, name="msflow-store-background", daemon=True).start()
    return future


def parse_marker(key: str, data: bytes) -> Json | None:
    """A commit marker's JSON when it is complete and names a manifest readers can use, else None."""
    try:
        marker = json_object(data)
        if "data" not in marker:
            return None
        check_manifest(key, marker["manifest"])
    except (ValueError, KeyError, CorruptArtifact):
        return None
    return marker


def _age(entry: dict[str, Any]) -> float:
    started = entry.get("started")
    return time.time() - started if isinstance(started, (int, float)) else float("inf")


class RemoteArray(StoredArray):
    """One stored output, read on demand (msflow.stored): chunk objects from this process's recent objects where
    it holds them, the rest fetched concurrently (and kept); zarr opened on the store for everything else, so
    lazy inputs behave as zarr arrays do on a local store."""

    def __init__(
        self,
        store: RemoteStore,
        folder: str,
        name: str,
        entry: dict[str, Any],
        chunks: list[Any] | None,
        checksum: bool = True,
        recent: RecentObjects | None = None,
        pack: PackSource | None = None,
    ):
        super().__init__(name, entry, chunks, checksum)
        self._store = store
        self._folder = folder
        self._recent = recent  # objects this process wrote or read lately (None: always ask the store)
        self._pack = pack  # the artifact's group as one object (msflow.stores.packs), shared by its outputs

    def _where(self) -> str:
        return f"{self._store.url}/{self._folder}"

    def _open_zarr(self) -> Any:
        if self._pack is not None:
            return self._pack.load().zarr_array(self._name)
        import zarr
        from zarr.storage import FsspecStore

        from msflow.stores.objects import s3_defaults

        protocol = self._store.url.split("://", 1)[0]
        options = s3_defaults(self._store.options) if protocol in ("s3", "s3a") else self._store.options
        zstore = FsspecStore.from_url(f"{self._store.url}/{self._folder}", storage_options=options, read_only=True)
        return zarr.open_array(zstore, path=self._name, mode="r")

    def _fetch(self, rels: list[str]) -> dict[str, bytes | None]:
        if self._pack is not None:
            pack = self._pack.load()
            return {rel: pack.get(rel) for rel in rels}
        recent = self._recent
        paths = {rel: f"{self._folder}/{rel}" for rel in rels}
        found = {rel: recent.get(path) if recent is not None else None for rel, path in paths.items()}
        missing = [rel for rel in rels if found[rel] is None]
        if missing:
            fetched = self._store.objects.get_many([paths[rel] for rel in missing])
            for rel in missing:
                found[rel] = data = fetched.get(paths[rel])
                if recent is not None and data is not None:
                    recent.put(paths[rel], data)
        return found


class PackSource:
    """An artifact's pack, fetched when one of its outputs is first read (from this process's recent objects
    when it holds them) and then shared by all of them."""

    def __init__(self, store: RemoteStore, path: str, recent: RecentObjects | None):
        self._store = store
        self._path = path
        self._recent = recent
        self._pack: Pack | None = None
        self._lock = threading.Lock()

    def load(self) -> Pack:
        with self._lock:
            if self._pack is None:
                data = self._recent.get(self._path) if self._recent is not None else None
                if data is None:
                    data = self._store.objects.get(self._path)
                    if data is None:
                        raise FileNotFoundError(f"{self._store.url}/{self._path} is missing")
                    if self._recent is not None:
                        self._recent.put(self._path, data)
                self._pack = Pack(data, f"{self._store.url}/{self._path}")
            return self._pack
