"""The artifact store on a local (or shared POSIX) file system.

Layout under the store root::

    artifacts/<k[:2]>/<key>/   one published zarr group per cache key (never modified once published)
    tmp/                       artifacts being written: <key>.<host>.<pid>.<nonce>; invisible to readers
    locks/<key>.lock           per-key flock; the kernel releases it when its holder dies, however it dies
    locks/store.lock           flock shared by the runs in progress, taken alone by gc (``in_use``)
    corrupt/<key>.<time>       artifacts found damaged on read, moved aside for inspection (with a .reason.txt)
    runs/<id>.json             one record per run
    cache/memo.json            memoised file hashes, code fingerprints and stage interfaces

Publishing is one ``rename`` of a complete temporary directory onto a fresh path, so a reader sees an artifact
whole or not at all, and a run killed at any moment leaves at most a directory under tmp/ that the next run
removes. Nothing is created until something is written: validation errors leave the store untouched.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msflow.atomic import write_json_atomic
from msflow.errors import StoreInUse, UserError
from msflow.stores.base import (
    HOST,
    Json,
    holder_fields,
    json_object,
    matching_run,
    pid_alive,
    record_object,
    run_record,
)

if TYPE_CHECKING:
    from msflow.artifact import ArtifactView


class LocalStore:
    """A store in a folder (see the module docstring for its layout); implements ``msflow.stores.base.Store``."""

    remote = False  # has() is a stat

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.url = str(self.root)
        self.local_cache: Path | None = self.root / "cache"
        self.options: dict[str, Any] = {}

    # ------------------------------------------------------------------ paths
    @property
    def artifacts_dir(self) -> Path:
        return self.root / "artifacts"

    def artifact_path(self, key: str) -> Path:
        return self.artifacts_dir / key[:2] / key

    def _dir(self, name: str) -> Path:
        path = self.root / name
        path.mkdir(parents=True, exist_ok=True)
        return path

    # ------------------------------------------------------------------ artifacts
    def has(self, key: str) -> bool:
        """Whether something is published under ``key`` (a damaged artifact counts: reading it raises
        CorruptArtifact, and the runner moves it aside)."""
        return self.artifact_path(key).is_dir()

    def manifest(self, key: str) -> Json:
        from msflow.artifact import read_manifest

        return read_manifest(self.artifact_path(key))

    def open(self, key: str) -> ArtifactView:
        from msflow.artifact import read_artifact

        return read_artifact(self.artifact_path(key), key=key)

    def keys(self) -> Iterator[str]:
        if not self.artifacts_dir.is_dir():
            return
        for prefix in sorted(self.artifacts_dir.iterdir()):
            if prefix.is_dir():
                for entry in sorted(prefix.iterdir()):
                    yield entry.name

    def writer(self, key: str) -> LocalWriter:
        """An artifact being written under ``key``: output sinks put chunks into it while the stage runs, then
        ``commit`` publishes it (use it as a context manager: leaving without a commit removes it)."""
        return LocalWriter(self, key)

    def write(
        self,
        key: str,
        arrays: Mapping[str, Any],
        extra: Json,
        file_suffixes: Mapping[str, str | None] | None = None,
        replace: bool = False,
    ) -> Json:
        """Write arrays and manifest under tmp/, then publish atomically; returns the manifest."""
        with self.writer(key) as writer:
            return writer.commit(arrays, extra, file_suffixes, replace)

    def temp_folder(self, key: str) -> Path:
        """A fresh private folder under tmp/ for writing ``key``, named so clean_tmp knows its writer."""
        path = self._dir("tmp") / f"{key}.{HOST}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        path.mkdir()
        return path

    def publish(self, tmp: Path, key: str, replace: bool) -> None:
        """Move a complete temporary folder to ``key``'s place in one rename."""
        target = self.artifact_path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        if replace and target.exists():
            trash = self._dir("tmp") / f"trash.{key}.{uuid.uuid4().hex[:8]}"
            os.rename(target, trash)
            shutil.rmtree(trash, ignore_errors=True)
        try:
            os.rename(tmp, target)
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
            if (target / "zarr.json").is_file():
                return  # published meanwhile by another writer of the same key: same content by construction
            self.quarantine(key, "an incomplete artifact folder was in the way of a new one")
            os.rename(tmp, target)

    def verify(self, key: str) -> list[str]:
        from msflow.artifact import verify_artifact

        return verify_artifact(self.artifact_path(key))

    def size(self, key: str) -> int:
        return _folder_bytes(self.artifact_path(key))

    def quarantine(self, key: str, reason: str) -> str:
        """Move a corrupt artifact aside to corrupt/<key>.<time> (kept for inspection, with the reason beside it);
        the key becomes free to recompute. Returns where it went."""
        target = self.artifact_path(key)
        if not target.exists():
            return ""
        aside = self._dir("corrupt") / f"{key}.{time.strftime('%Y%m%dT%H%M%S')}.{uuid.uuid4().hex[:6]}"
        os.rename(target, aside)
        aside.with_name(aside.name + ".reason.txt").write_text(reason + "\n", encoding="utf-8")
        return str(aside)

    def drop_quarantined(self, *, dry_run: bool = False) -> tuple[list[str], int]:
        """Delete the artifacts ``quarantine`` set aside, with their reasons; returns their names and bytes."""
        aside = self.root / "corrupt"
        entries = sorted(aside.iterdir()) if aside.is_dir() else []
        names = [e.name for e in entries if not e.name.endswith(".reason.txt")]
        freed = sum(_folder_bytes(e) for e in entries)
        if not dry_run:
            for entry in entries:
                if entry.is_dir():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink(missing_ok=True)
        return names, freed

    def remove(self, key: str) -> None:
        target = self.artifact_path(key)
        if target.exists():
            trash = self._dir("tmp") / f"trash.{key}.{uuid.uuid4().hex[:8]}"
            os.rename(target, trash)
            shutil.rmtree(trash, ignore_errors=True)

    def clean_tmp(self, *, max_age: float | None = None) -> list[str]:
        """Remove temporary directories whose writer is gone (or older than max_age seconds)."""
        tmp = self.root / "tmp"
        removed: list[str] = []
        if not tmp.is_dir():
            return removed
        for entry in tmp.iterdir():
            parts = entry.name.split(".")
            dead = True
            if len(parts) >= 4 and parts[0] != "trash" and parts[-3] == HOST:
                dead = not pid_alive(int(parts[-2])) if parts[-2].isdigit() else True
            elif len(parts) >= 4 and parts[0] != "trash":
                dead = max_age is not None and time.time() - entry.stat().st_mtime > max_age
            if dead:
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(entry.name)
        return removed

    # ------------------------------------------------------------------ locks
    @contextlib.contextmanager
    def lock(self, key: str, on_wait: Callable[[Json], None] | None = None, poll: float = 0.05) -> Iterator[None]:
        """Exclusive per-key lock across processes and concurrent runs.

        flock locks belong to the open file description: when the holder dies (even by SIGKILL) the kernel drops
        the lock, so a lock left behind by a dead run is broken by construction; the holder's host and pid are
        written into the file for ``msflow status`` and error messages.
        """
        import fcntl

        path = self._lock_file(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            waited = False
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if not waited and on_wait is not None:
                        on_wait(read_holder(path))
                    waited = True
                    time.sleep(poll)
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps({**holder_fields(), "since": time.time()}).encode())
            yield
        finally:
            with contextlib.suppress(OSError):
                fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def _lock_file(self, key: str) -> Path:
        return self.root / "locks" / f"{key}.lock"

    def computing(self, key: str) -> Json | None:
        """The holder of the key's flock (a run computing it now), probed with a shared lock that is let go at
        once; None when nobody holds it. Creates nothing."""
        import fcntl

        path = self._lock_file(key)
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            return None  # never locked
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return read_holder(path)
        else:
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    @contextlib.contextmanager
    def in_use(self, *, alone: bool = False, on_wait: Callable[[Json], None] | None = None) -> Iterator[None]:
        """A shared flock on locks/store.lock held by runs; gc's exclusive one fails at once while any run holds
        it (the kernel drops a dead run's hold, so a killed run never blocks gc). A run starting while gc holds
        it waits (``on_wait`` told first)."""
        import fcntl

        fd = os.open(self._dir("locks") / "store.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB if alone else fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                if alone:
                    raise StoreInUse(
                        f"a run is using the store {self.url} (msflow run or sweep): gc would delete the artifacts "
                        "it is making before its record names them; run gc once it has ended"
                    ) from None
                if on_wait is not None:
                    on_wait({})  # gc holds it (a flock names nobody)
                fcntl.flock(fd, fcntl.LOCK_SH)
            yield
        finally:
            os.close(fd)  # releases the lock

    # ------------------------------------------------------------------ memo, runs
    def load_memo(self) -> Json:
        try:
            return json_object((self.root / "cache" / "memo.json").read_bytes())
        except (OSError, ValueError):
            return {}

    def save_memo(self, memo: Json) -> None:
        write_json_atomic(self._dir("cache") / "memo.json", memo)

    def write_run(self, record: Json) -> str:
        path = self._dir("runs") / f"{record['id']}.json"
        write_json_atomic(path, record, indent=1)
        return str(path)

    def run_ids(self) -> list[str]:
        runs = self.root / "runs"
        return sorted(p.stem for p in runs.glob("*.json")) if runs.is_dir() else []

    def read_run(self, run_id: str) -> Json:
        path = self.root / "runs" / f"{run_id}.json"
        if not path.is_file():
            path = self.root / "runs" / f"{matching_run(run_id, self.run_ids(), str(self.root))}.json"
        return run_record(path.read_bytes(), str(path), self._read_raw_run)

    def _read_raw_run(self, run_id: str) -> Json:
        return json_object((self.root / "runs" / f"{run_id}.json").read_bytes())

    def write_sweep(self, record: Json) -> str:
        path = self._dir("sweeps") / f"{record['id']}.json"
        write_json_atomic(path, record, indent=1)
        return str(path)

    def sweep_ids(self) -> list[str]:
        sweeps = self.root / "sweeps"
        return sorted(p.stem for p in sweeps.glob("*.json")) if sweeps.is_dir() else []

    def read_sweep(self, sweep_id: str) -> Json:
        path = self.root / "sweeps" / f"{sweep_id}.json"
        if not path.is_file():
            raise UserError(f"no sweep '{sweep_id}'", file=str(self.root))
        return record_object(path.read_bytes(), str(path))

    def remove_run(self, run_id: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            (self.root / "runs" / f"{run_id}.json").unlink()


class LocalWriter:
    """One artifact being written: a private folder under tmp/ (created on the first write), published by one
    rename. A writer killed at any moment leaves only that folder, which clean_tmp removes."""

    def __init__(self, store: LocalStore, key: str):
        self.store = store
        self.key = key
        self.path: Path | None = None
        self._made: set[Path] = set()

    def __enter__(self) -> LocalWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.abort()

    def _folder(self) -> Path:
        if self.path is None:
            self.path = self.store.temp_folder(self.key)
            self._made.add(self.path)
        return self.path

    def put(self, rel: str, data: bytes) -> None:
        """Write one file of the zarr group (a chunk of an output sink) now."""
        target = self._folder() / rel
        if target.parent not in self._made:
            target.parent.mkdir(parents=True, exist_ok=True)
            self._made.add(target.parent)
        with open(target, "wb") as fh:
            fh.write(data)

    def commit(
        self,
        arrays: Mapping[str, Any],
        extra: Json,
        file_suffixes: Mapping[str, str | None] | None = None,
        replace: bool = False,
    ) -> Json:
        """Write the remaining arrays and the manifest, then publish; returns the manifest."""
        from msflow.artifact import encode_artifact, prepare_manifest

        arrays, manifest = prepare_manifest(arrays, extra, file_suffixes)
        folder = self._folder()
        for entry in folder.iterdir():  # chunks of sinks the stage opened but did not return
            if entry.name not in arrays:
                shutil.rmtree(entry, ignore_errors=True)
        for rel, data in encode_artifact(arrays, manifest):
            self.put(rel, data)
        self.store.publish(folder, self.key, replace)
        return manifest

    def abort(self) -> None:
        """Remove whatever was written (nothing once committed: the folder became the artifact)."""
        if self.path is not None and self.path.exists():
            shutil.rmtree(self.path, ignore_errors=True)


def _folder_bytes(path: Path) -> int:
    """The bytes of the files in ``path`` (a folder, walked; or a file)."""
    if path.is_file():
        return path.stat().st_size
    total = 0
    for dirpath, _, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):
                total += os.path.getsize(os.path.join(dirpath, name))
    return total


def read_holder(path: Path) -> Json:
    """The host and pid a lock file names (empty when unreadable)."""
    try:
        return json_object(path.read_text() or "{}")
    except (OSError, ValueError):
        return {}
