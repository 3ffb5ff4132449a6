"""What a process recently wrote to or read from an object store, kept so the next stage need not ask again.

A chain of stages run by one process (``-j 1``, or a Dask worker that runs consecutive stages) reads, as input,
the artifact it committed a moment ago: one GET for its commit marker and one per chunk, each a round trip on the
critical path. Two caches answer them from memory:

``RecentObjects``
    The objects of artifacts' data folders, by path, bytes-bounded, least recently used out first. Those objects
    are immutable (a folder belongs to one writer and is never rewritten; ``--force`` writes a new folder), so an
    entry can never be stale: it holds exactly what the server holds, or held before a removal. Chunks carry
    their crc32c into the cache and are checked when decoded, as fetched ones are; ``msflow verify`` reads the
    server, never the cache. Capacity: ``MSFLOW_STORE_CACHE_MB`` (default 64, 0 switches both caches off).
``RecentMarkers``
    Commit markers this process wrote or read, each for ``MARKER_SECONDS``. A marker can be replaced
    (``--force``) or removed meanwhile; a reader that holds an old marker reads the folder it names, which
    ``--force`` keeps readable for ``RETIRE_SECONDS`` (msflow.stores.remote) - the same promise a reader that
    fetched the marker a moment ago relies on, so the age limit stays well inside it. ``has`` always asks the
    server; only reading a key known to exist (``manifest``, ``open``) uses a remembered marker.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Any

from msflow.stores.base import env_megabytes

DEFAULT_MB = 64
MARKER_SECONDS = 15.0  # a quarter of RETIRE_SECONDS (msflow.stores.remote)


def cache_bytes() -> int:
    """The object cache's capacity in bytes: ``MSFLOW_STORE_CACHE_MB`` (default 64) megabytes."""
    return env_megabytes("MSFLOW_STORE_CACHE_MB", DEFAULT_MB)


class RecentObjects:
    """A thread-safe, bytes-bounded LRU of immutable objects (path -> bytes); an object larger than an eighth of
    the capacity is not kept (it would evict everything else for one read)."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.size = 0
        self._items: OrderedDict[str, bytes] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, path: str) -> bytes | None:
        with self._lock:
            data = self._items.get(path)
            if data is not None:
                self._items.move_to_end(path)
            return data

    def put(self, path: str, data: bytes) -> None:
        if len(data) > self.capacity // 8:
            return
        with self._lock:
            old = self._items.pop(path, None)
            self.size += len(data) - (len(old) if old is not None else 0)
            self._items[path] = data
            while self.size > self.capacity:
                _, evicted = self._items.popitem(last=False)
                self.size -= len(evicted)


class RecentMarkers:
    """Commit markers by key, each usable for ``max_age`` seconds after it was written or read."""

    def __init__(self, max_age: float = MARKER_SECONDS):
        self.max_age = max_age
        self._items: dict[str, tuple[dict[str, Any], float]] = {}
        self._lock = threading.Lock()

    def get(self, key: str) -> dict[str, Any] | None:
        with self._lock:
            found = self._items.get(key)
            if found is None:
                return None
            if time.monotonic() - found[1] > self.max_age:
                del self._items[key]
                return None
            return found[0]

    def put(self, key: str, marker: dict[str, Any]) -> None:
        with self._lock:
            if len(self._items) > 10_000:  # bounded: drop whatever has expired
                now = time.monotonic()
                self._items = {k: v for k, v in self._items.items() if now - v[1] <= self.max_age}
            self._items[key] = (marker, time.monotonic())

    def forget(self, key: str) -> None:
        with self._lock:
            self._items.pop(key, None)


class RecentCaches:
    """The two caches of one store (one URL) in this process."""

    def __init__(self, capacity: int):
        self.objects = RecentObjects(capacity)
        self.markers = RecentMarkers()
        self.enabled = capacity > 0


_CACHES: dict[str, RecentCaches] = {}
_CACHES_LOCK = threading.Lock()


def caches_for(url: str) -> RecentCaches:
    """This process's caches for the store at ``url`` (shared by every RemoteStore opened on it)."""
    with _CACHES_LOCK:
        caches = _CACHES.get(url)
        if caches is None:
            caches = _CACHES[url] = RecentCaches(cache_bytes())
        return caches
