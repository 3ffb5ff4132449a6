"""Per-key leases on an object store: the remote counterpart of LocalStore's flock.

A lease is one small JSON object ``locks/<key>.lease`` naming its holder (host, pid, a random token) and its
time to live. Protocol:

acquire
    Create the object with a conditional PUT (``If-None-Match: *``): of several writers racing, the server lets
    exactly one through, and the winner holds the etag the PUT returned. Where create is not atomic - an
    S3-compatible server that ignores the condition (each process asks its server once,
    ``Objects.creates_exclusively``) or a backend without conditional writes (FsspecObjects) - create reads before
    it writes, and the winner waits ``settle`` seconds, so that a concurrent writer who checked before our write
    but wrote after it is seen, then reads the object back and proceeds only if it carries its own token.
hold
    A daemon thread renews the lease every ttl/3 with ``If-Match: <etag>``; a failed renewal means the lease was
    broken (the holder stalled for longer than the ttl) and is recorded in ``lost``.
wait / break
    A waiter polls. A lease is broken, by a delete conditional on the etag it inspected (so a renewal in between
    wins), when it expired - older than its ttl (plus a margin) by the server's clock - or when its holder ran on
    this host and that process is gone (a SIGKILLed run frees its keys at once, as flock does locally).
release
    Stop the heartbeat, delete the lease if it still has our etag. RemoteStore.lock sends the release when its
    block ends without waiting for it (its round trip overlaps the next stage); the process settles its releases
    in flight when a run ends and before it exits (msflow.stores.remote.settle_releases), and locking the same key
    again first waits for its own release.

Leases make "each stage instance computed once" hold across machines; they are not what keeps the store
consistent. Publishing is atomic and content-addressed (msflow.stores.remote), so a lost lease costs duplicated work,
never a torn or mixed artifact.
"""

from __future__ import annotations

import json
import os
import threading
import time
import uuid
from typing import Any, Callable

from msflow.stores.base import HOST, holder_fields, pid_alive
from msflow.stores.objects import Objects

DEFAULT_TTL = 60.0
SKEW = 2.0  # seconds of grace beyond a lease's ttl before it is broken (clock and timestamp granularity)


def lease_ttl() -> float:
    """Lease time to live in seconds: 60, or MSFLOW_LEASE_SECONDS."""
    try:
        return max(1.0, float(os.environ.get("MSFLOW_LEASE_SECONDS", DEFAULT_TTL)))
    except ValueError:
        return DEFAULT_TTL


def parse_holder(data: bytes) -> dict[str, Any]:
    try:
        holder = json.loads(data)
        return holder if isinstance(holder, dict) else {}
    except ValueError:
        return {}


def lease_is_stale(holder: dict[str, Any], age: float | None, now: float | None = None) -> bool:
    """Whether a lease may be broken: its holder on this host is gone, or it was not renewed within its ttl."""
    if holder.get("host") == HOST and isinstance(holder.get("pid"), int) and not pid_alive(holder["pid"]):
        return True
    raw_ttl = holder.get("ttl")
    ttl = float(raw_ttl) if isinstance(raw_ttl, (int, float)) else DEFAULT_TTL
    if age is not None:  # server clock: immune to skew between machines
        return age > ttl + SKEW
    renewed = holder.get("renewed")
    if not isinstance(renewed, (int, float)):
        return False
    return (now or time.time()) > renewed + ttl + SKEW


class Lease:
    def __init__(self, objects: Objects, path: str, ttl: float | None = None, settle: float = 0.5):
        self.objects = objects
        self.path = path
        self.ttl = ttl or lease_ttl()
        self.settle = settle  # where create is not atomic: wait this long before reading the lease back
        self.token = uuid.uuid4().hex
        self.since = 0.0
        self.etag: str | None = None
        self.lost = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _body(self) -> bytes:
        return json.dumps(
            {
                "owner": self.token,
                **holder_fields(),
                "since": self.since,
                "renewed": time.time(),
                "ttl": self.ttl,
            }
        ).encode()

    def acquire(
        self, on_wait: Callable[[dict[str, Any]], None] | None = None, poll: float = 0.1, timeout: float | None = None
    ) -> None:
        self.since = time.time()
        deadline = None if timeout is None else time.monotonic() + timeout
        told = False
        delay = poll
        while True:
            created = self.objects.create(self.path, self._body())
            if created is not None and self.objects.creates_exclusively():
                self.etag = created  # the server refused every other creator: no need to read it back
                self._start_heartbeat()
                return
            if created is not None:
                time.sleep(self.settle)
                current = self.objects.get_versioned(self.path)
                if current is not None and parse_holder(current.data).get("owner") == self.token:
                    self.etag = current.etag
                    self._start_heartbeat()
                    return
            else:
                current = self.objects.get_versioned(self.path)
            if current is None:
                continue  # released between our attempt and the read: try again at once
            holder = parse_holder(current.data)
            if lease_is_stale(holder, current.age):
                self.objects.delete_if(self.path, current.etag)
                continue
            if not told and on_wait is not None:
                on_wait(holder)
                told = True
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"lease {self.path} held by {holder}")
            time.sleep(delay)
            delay = min(delay * 1.5, 1.0)

    def take_fresh(self) -> None:
        """Hold a lease at a path nobody contends for (a new token in its name): one plain PUT, then renewals."""
        self.since = time.time()
        self.etag = self.objects.put(self.path, self._body())
        self._start_heartbeat()

    def _start_heartbeat(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._heartbeat, name=f"msflow-lease-{self.path}", daemon=True)
        self._thread.start()

    def _heartbeat(self) -> None:
        while not self._stop.wait(self.ttl / 3):
            if self.etag is None:
                return
            try:
                etag = self.objects.replace_if(self.path, self._body(), self.etag)
            except Exception:
                continue
            if etag is None:
                self.lost = True
                return
            self.etag = etag

    def release(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if not self.lost and self.etag is not None:
            self.objects.delete_if(self.path, self.etag)
        self.etag = None


PRESENCE_PREFIX = "active/"
GC_PREFIX = "gc/"


class Presence:
    """A process's presence on a store, ``<prefix><token>.lease``: a lease nobody else contends for (its path is
    new), so it is written with a plain PUT and renewed every ttl/3 by a daemon thread. Runs are present under
    ``active/``, which ``msflow gc`` reads (``live_presences``) to know whether runs are using the store; gc is
    present under ``gc/``, which a starting run reads to wait for it. Released (deleted) at the end; a killed
    process's goes stale by the lease rules (its pid gone on this host, or not renewed within its ttl)."""

    def __init__(self, objects: Objects, ttl: float | None = None, prefix: str = PRESENCE_PREFIX):
        self.lease = Lease(objects, f"{prefix}{uuid.uuid4().hex}.lease", ttl)

    def __enter__(self) -> Presence:
        self.lease.take_fresh()
        return self

    def __exit__(self, *exc: object) -> None:
        self.lease.release()


def live_presences(objects: Objects, prefix: str = PRESENCE_PREFIX) -> list[dict[str, Any]]:
    """The holders of the presences under ``prefix`` now (runs by default); stale ones (killed processes) are
    deleted on the way."""
    live = []
    for info in objects.list(prefix):
        current = objects.get_versioned(info.path)
        if current is None:
            continue
        holder = parse_holder(current.data)
        if lease_is_stale(holder, current.age):
            objects.delete_if(info.path, current.etag)
        else:
            live.append(holder)
    return live
