"""Object access for remote stores: the handful of primitives msflow.stores.remote needs, and translation of backend
failures (credentials, bucket, network) into UserErrors that name the store.

Two backends:

``S3Objects``
    S3 and S3-compatible servers through s3fs's botocore client, one request per primitive (no HEAD before a
    GET, no listing cache). Conditional writes are real: ``create`` is a PUT with ``If-None-Match: *`` (each
    process asks the server once whether it honours that, ``creates_exclusively``; if not, create reads first),
    ``replace_if``/``delete_if`` carry ``If-Match: <etag>``, and the age of an object is measured on the server's
    clock (``Date`` minus ``Last-Modified``), so clock skew between machines does not matter.
``FsspecObjects``
    Any other fsspec filesystem (``memory://``, ``gcs://`` ...). Conditional operations are emulated by
    read-compare-write and are not atomic; msflow.stores.leases compensates with a settle delay.

Paths given to these methods are relative to the store's root.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import os
import uuid
from collections.abc import Awaitable, Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from msflow.errors import UserError
from msflow.stores.base import HOST

T = TypeVar("T")

PROBE_SECONDS = 15.0  # the first request to a store gives up after this long (MSFLOW_STORE_TIMEOUT)
CONCURRENCY = 16  # parallel requests when reading or writing many objects
_EXCLUSIVE_CREATE: dict[tuple[str | None, str], bool] = {}  # (endpoint, bucket) -> server honours If-None-Match


def probe_seconds() -> float:
    """How long the first request to a store may take before the endpoint counts as unreachable."""
    try:
        return max(0.1, float(os.environ.get("MSFLOW_STORE_TIMEOUT", PROBE_SECONDS)))
    except ValueError:
        return PROBE_SECONDS


@dataclass
class Versioned:
    """An object's bytes with its version tag; ``age`` is seconds since it was last written by the server's clock
    (None when the backend cannot tell)."""

    data: bytes
    etag: str
    age: float | None = None


@dataclass
class ObjectInfo:
    path: str  # relative to the store root
    size: int


def _client_error_code(exc: BaseException) -> str | None:
    """The S3 error code behind an exception s3fs translated (it keeps the botocore error as __cause__)."""
    seen = 0
    current: BaseException | None = exc
    while current is not None and seen < 5:
        response = getattr(current, "response", None)
        if isinstance(response, dict):
            error = response.get("Error", {})
            code = error.get("Code")
            if code:
                return str(code)
            status = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
            if status:
                return str(status)
        current = current.__cause__ or current.__context__
        seen += 1
    return None


PRECONDITION_CODES = {"PreconditionFailed", "412", "ConditionalRequestConflict", "409"}
MISSING_CODES = {"NoSuchKey", "404"}


def translate_failure(exc: BaseException, url: str, endpoint: str | None = None) -> UserError | None:
    """A UserError for failures the user must fix (credentials, bucket, network, permissions), else None."""
    where = f"store {url}" + (f" (endpoint {endpoint})" if endpoint else "")
    name = type(exc).__name__
    code = _client_error_code(exc)
    if isinstance(exc, TypeError) and "unexpected keyword argument" in str(exc):
        return UserError(f"invalid store_options for {where}: {exc}", field="store_options")
    if name in ("NoCredentialsError", "PartialCredentialsError", "CredentialRetrievalError"):
        return UserError(
            f"no credentials for {where}: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY (or "
            "AWS_PROFILE) in the environment, or key and secret in store_options"
        )
    if code == "NoSuchBucket" or (isinstance(exc, FileNotFoundError) and "bucket does not exist" in str(exc)):
        return UserError(
            f"the bucket of {where} does not exist; create it first (msflow creates objects, never buckets)"
        )
    if code in (
        "InvalidAccessKeyId",
        "SignatureDoesNotMatch",
        "ExpiredToken",
        "InvalidToken",
        "AccessDenied",
        "AllAccessDisabled",
        "403",
    ) or isinstance(exc, PermissionError):
        return UserError(
            f"access denied to {where}: {exc} (check the credentials and their permissions on the bucket and prefix)"
        )
    network = (
        "EndpointConnectionError",
        "ConnectTimeoutError",
        "ReadTimeoutError",
        "ConnectionClosedError",
        "ProxyConnectionError",
        "SSLError",
        "ClientConnectorError",
        "ServerDisconnectedError",
        "ClientOSError",
        "TimeoutError",
    )
    if name in network or isinstance(exc, (ConnectionError, asyncio.TimeoutError, TimeoutError)):
        detail = str(exc) or f"no answer within {probe_seconds():g} s"
        return UserError(f"cannot reach {where}: {name}: {detail}")
    return None


class Objects(Protocol):
    """The object primitives a remote store is built on; paths are relative to the store's root."""

    def probe(self) -> None: ...
    def creates_exclusively(self) -> bool: ...
    def get(self, rel: str) -> bytes | None: ...
    def get_versioned(self, rel: str) -> Versioned | None: ...
    def get_many(self, rels: list[str]) -> dict[str, bytes | None]: ...
    def exists_many(self, rels: list[str]) -> dict[str, bool]: ...
    def put(self, rel: str, data: bytes) -> str: ...
    def put_many(self, items: dict[str, bytes]) -> None: ...
    def create(self, rel: str, data: bytes) -> str | None: ...
    def replace_if(self, rel: str, data: bytes, etag: str) -> str | None: ...
    def delete_if(self, rel: str, etag: str) -> bool: ...
    def delete(self, rel: str) -> None: ...
    def list(self, rel_prefix: str) -> list[ObjectInfo]: ...
    def delete_prefix(self, rel_prefix: str) -> int: ...


class S3Objects:
    def __init__(self, fs: Any, bucket: str, prefix: str, url: str):
        self.fs = fs
        self.bucket = bucket
        self.prefix = prefix.strip("/")
        self.url = url
        self.endpoint = getattr(fs, "endpoint_url", None) or (fs.client_kwargs or {}).get("endpoint_url")

    # ------------------------------------------------------------------ plumbing
    def _key(self, rel: str) -> str:
        return f"{self.prefix}/{rel}" if self.prefix else rel

    def _rel(self, key: str) -> str:
        return key[len(self.prefix) + 1 :] if self.prefix else key

    def _run(self, coro_fn: Callable[..., Awaitable[T]], *args: Any) -> T:
        from fsspec.asyn import sync

        try:
            result: T = sync(self.fs.loop, coro_fn, *args)
            return result
        except Exception as exc:
            error = translate_failure(exc, self.url, self.endpoint)
            if error is not None:
                raise error from None
            raise

    async def _call(self, method: str, **kwargs: Any) -> dict[str, Any]:
        response: dict[str, Any] = await self.fs._call_s3(method, Bucket=self.bucket, **kwargs)
        return response

    async def _aget(self, rel: str) -> bytes | None:
        got = await self._aget_versioned(rel)
        return None if got is None else got.data

    async def _aget_versioned(self, rel: str) -> Versioned | None:
        try:
            resp = await self._call("get_object", Key=self._key(rel))
        except FileNotFoundError as exc:
            if _client_error_code(exc) == "NoSuchBucket" or "bucket does not exist" in str(exc):
                raise
            return None
        try:
            body: bytes = await resp["Body"].read()
        finally:
            resp["Body"].close()
        age = None
        date = resp.get("ResponseMetadata", {}).get("HTTPHeaders", {}).get("date")
        if date and resp.get("LastModified") is not None:
            from email.utils import parsedate_to_datetime

            age = (parsedate_to_datetime(date) - resp["LastModified"]).total_seconds()
        return Versioned(body, resp["ETag"], age)

    async def _gather(self, coros: list[Awaitable[T]]) -> list[T]:
        semaphore = asyncio.Semaphore(CONCURRENCY)

        async def limited(coro: Awaitable[T]) -> T:
            async with semaphore:
                return await coro

        return list(await asyncio.gather(*(limited(c) for c in coros)))

    # ------------------------------------------------------------------ primitives
    def probe(self) -> None:
        """One cheap request that fails clearly when the bucket, credentials or endpoint are wrong."""

        async def list_one() -> dict[str, Any]:
            return await asyncio.wait_for(
                self._call("list_objects_v2", Prefix=self._key(""), MaxKeys=1), probe_seconds()
            )

        self._run(list_one)

    def creates_exclusively(self) -> bool:
        """Whether this server refuses ``create`` of an existing object (honours ``If-None-Match: *``), so the
        etag ``create`` returns is proof of ownership. Some S3-compatible servers ignore the condition; asked once
        per process and server (three requests: create a probe object, create it again, delete it)."""
        server = (self.endpoint, self.bucket)
        if server not in _EXCLUSIVE_CREATE:
            answer = self._probe_exclusive_create()
            if answer is None:
                return False  # no answer this time: the safe path now, ask again next time
            _EXCLUSIVE_CREATE[server] = answer
        return _EXCLUSIVE_CREATE[server]

    def _probe_exclusive_create(self) -> bool | None:
        # a body clean_tmp can judge like a lease's, should this process die before deleting it
        path = f"locks/.create-probe-{uuid.uuid4().hex}"
        body = json.dumps({"probe": "If-None-Match", "host": HOST, "pid": os.getpid(), "ttl": 1.0}).encode()
        try:
            if self._run(self._create_if_absent, path, body) is None:
                return None  # our fresh name existed: nothing learnt
            return self._run(self._create_if_absent, path, body) is None
        except Exception:
            return None  # a failed request says nothing about the server's conditions
        finally:
            with contextlib.suppress(Exception):
                self.delete(path)

    def get(self, rel: str) -> bytes | None:
        return self._run(self._aget, rel)

    def get_versioned(self, rel: str) -> Versioned | None:
        return self._run(self._aget_versioned, rel)

    def get_many(self, rels: list[str]) -> dict[str, bytes | None]:
        async def fetch() -> list[bytes | None]:
            return await self._gather([self._aget(r) for r in rels])

        return dict(zip(rels, self._run(fetch)))

    def exists_many(self, rels: list[str]) -> dict[str, bool]:
        """Whether each object exists: one listing of its exact key each, sent concurrently."""

        async def exists(rel: str) -> bool:
            resp = await self._call("list_objects_v2", Prefix=self._key(rel), MaxKeys=1)
            return any(o["Key"] == self._key(rel) for o in resp.get("Contents", []))

        async def check_all() -> list[bool]:
            return await self._gather([exists(r) for r in rels])

        return dict(zip(rels, self._run(check_all))) if rels else {}

    def put(self, rel: str, data: bytes) -> str:
        async def put() -> str:
            return str((await self._call("put_object", Key=self._key(rel), Body=data))["ETag"])

        return self._run(put)

    def put_many(self, items: dict[str, bytes]) -> None:
        async def put_all() -> None:
            await self._gather([self._call("put_object", Key=self._key(r), Body=d) for r, d in items.items()])

        self._run(put_all)

    async def _conditional(self, method: str, **kwargs: Any) -> dict[str, Any] | None:
        try:
            return await self._call(method, **kwargs)
        except (OSError, ValueError) as exc:
            code = _client_error_code(exc)
            if (
                code in PRECONDITION_CODES
                or code in MISSING_CODES
                or isinstance(exc, FileExistsError)
                or (isinstance(exc, FileNotFoundError) and code != "NoSuchBucket")
            ):
                return None
            raise

    async def _create_if_absent(self, rel: str, data: bytes) -> str | None:
        resp = await self._conditional("put_object", Key=self._key(rel), Body=data, IfNoneMatch="*")
        return None if resp is None else str(resp["ETag"])

    def create(self, rel: str, data: bytes) -> str | None:
        """Write ``rel`` only if no object is there; its etag, or None if one existed. Atomic on a server that
        honours ``If-None-Match``; elsewhere a read before the write, which narrows the race to the two requests'
        interval (msflow.stores.leases settles and reads back there)."""
        if not self.creates_exclusively() and self.get(rel) is not None:
            return None
        return self._run(self._create_if_absent, rel, data)

    def replace_if(self, rel: str, data: bytes, etag: str) -> str | None:
        """Overwrite ``rel`` only if it is still at version ``etag``; the new etag, or None."""

        async def replace() -> str | None:
            resp = await self._conditional("put_object", Key=self._key(rel), Body=data, IfMatch=etag)
            return None if resp is None else str(resp["ETag"])

        return self._run(replace)

    def delete_if(self, rel: str, etag: str) -> bool:
        async def delete() -> bool:
            return await self._conditional("delete_object", Key=self._key(rel), IfMatch=etag) is not None

        return self._run(delete)

    def delete(self, rel: str) -> None:
        async def delete() -> None:
            try:
                await self._call("delete_object", Key=self._key(rel))
            except FileNotFoundError as exc:
                if _client_error_code(exc) == "NoSuchBucket":
                    raise

        self._run(delete)

    async def _alist(self, rel_prefix: str) -> list[ObjectInfo]:
        found: list[ObjectInfo] = []
        token = None
        while True:
            kwargs = {"Prefix": self._key(rel_prefix)}
            if token:
                kwargs["ContinuationToken"] = token
            resp = await self._call("list_objects_v2", **kwargs)
            found.extend(ObjectInfo(self._rel(o["Key"]), int(o.get("Size", 0))) for o in resp.get("Contents", []))
            if not resp.get("IsTruncated"):
                return found
            token = resp.get("NextContinuationToken")

    def list(self, rel_prefix: str) -> list[ObjectInfo]:
        """Every object whose path starts with ``rel_prefix`` (end it with '/' for a folder)."""
        return self._run(self._alist, rel_prefix)

    def delete_prefix(self, rel_prefix: str) -> int:
        async def delete_all() -> int:
            objects = await self._alist(rel_prefix)
            keys = [self._key(o.path) for o in objects]
            for start in range(0, len(keys), 1000):
                batch = [{"Key": k} for k in keys[start : start + 1000]]
                await self._call("delete_objects", Delete={"Objects": batch, "Quiet": True})
            return len(keys)

        return self._run(delete_all)


class FsspecObjects:
    """Any fsspec filesystem. ``create``/``replace_if``/``delete_if`` are read-compare-write, not atomic."""

    def __init__(self, fs: Any, root: str, url: str):
        self.fs = fs
        self.root = root.rstrip("/")
        self.url = url

    def _abs(self, rel: str) -> str:
        return f"{self.root}/{rel}"

    def _guard(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except FileNotFoundError:
            raise
        except Exception as exc:
            error = translate_failure(exc, self.url)
            if error is not None:
                raise error from None
            raise

    @staticmethod
    def _etag(data: bytes) -> str:
        return hashlib.blake2b(data, digest_size=16).hexdigest()

    def probe(self) -> None:
        self._guard(self.fs.exists, self.root)

    def creates_exclusively(self) -> bool:
        return False  # create is read-then-write here

    def get(self, rel: str) -> bytes | None:
        try:
            data: bytes = self._guard(self.fs.cat_file, self._abs(rel))
            return data
        except (FileNotFoundError, IsADirectoryError):
            return None

    def get_versioned(self, rel: str) -> Versioned | None:
        data = self.get(rel)
        return None if data is None else Versioned(data, self._etag(data))

    def get_many(self, rels: list[str]) -> dict[str, bytes | None]:
        if not rels:
            return {}
        paths = [self._abs(r) for r in rels]
        got = self._guard(self.fs.cat, paths, on_error="return")
        return {r: (None if isinstance(got.get(p), Exception) else got.get(p)) for r, p in zip(rels, paths)}

    def exists_many(self, rels: list[str]) -> dict[str, bool]:
        return {rel: bool(self._guard(self.fs.isfile, self._abs(rel))) for rel in rels}

    def put(self, rel: str, data: bytes) -> str:
        self._guard(self.fs.pipe_file, self._abs(rel), data)
        return self._etag(data)

    def put_many(self, items: dict[str, bytes]) -> None:
        if items:
            self._guard(self.fs.pipe, {self._abs(r): d for r, d in items.items()})

    def create(self, rel: str, data: bytes) -> str | None:
        if self.get(rel) is not None:
            return None
        return self.put(rel, data)

    def replace_if(self, rel: str, data: bytes, etag: str) -> str | None:
        current = self.get_versioned(rel)
        if current is None or current.etag != etag:
            return None
        return self.put(rel, data)

    def delete_if(self, rel: str, etag: str) -> bool:
        current = self.get_versioned(rel)
        if current is None or current.etag != etag:
            return False
        self.delete(rel)
        return True

    def delete(self, rel: str) -> None:
        try:
            self._guard(self.fs.rm_file, self._abs(rel))
        except FileNotFoundError:
            pass

    def list(self, rel_prefix: str) -> list[ObjectInfo]:
        base, _, _ = rel_prefix.rpartition("/")
        folder = self._abs(base) if base else self.root
        self.fs.invalidate_cache(folder)
        try:
            found = self._guard(self.fs.find, folder, detail=True)
        except FileNotFoundError:
            return []
        out = []
        for path, info in found.items():
            path = path if path.startswith("/") or not self.root.startswith("/") else "/" + path
            rel = path[len(self.root) + 1 :]
            if rel.startswith(rel_prefix) and info.get("type", "file") == "file":
                out.append(ObjectInfo(rel, int(info.get("size") or 0)))
        return sorted(out, key=lambda o: o.path)

    def delete_prefix(self, rel_prefix: str) -> int:
        objects = self.list(rel_prefix)
        for obj in objects:
            self.delete(obj.path)
        return len(objects)


# One filesystem (one botocore client: ~0.1 s to create) per process and set of options, shared by every store
# opened on it: a worker opens the store once per job.
_FILESYSTEMS: dict[str, object] = {}


def make_objects(url: str, options: dict[str, Any]) -> Objects:
    """The object backend for ``scheme://bucket/prefix``; raises UserError when fsspec cannot serve the scheme."""
    protocol, _, rest = url.partition("://")
    try:
        import fsspec
    except ImportError:
        raise UserError(f"store {url}: remote stores need fsspec (pip install 'msflow[s3]' for S3)") from None
    try:
        cls = fsspec.get_filesystem_class(protocol)
    except ImportError as exc:
        raise UserError(f"store {url}: no fsspec implementation for '{protocol}://' is installed: {exc}") from None
    except ValueError:
        from fsspec.registry import known_implementations

        known = ", ".join(sorted(p for p in known_implementations if len(p) <= 5)[:20])
        raise UserError(f"store {url}: unknown URL scheme '{protocol}://' (fsspec knows {known}, ...)") from None
    if not isinstance(options, dict):
        raise UserError(
            f"store_options must be a mapping of fsspec storage options, got {options!r}", field="store_options"
        )
    is_s3 = protocol in ("s3", "s3a") and cls.__module__.startswith("s3fs")
    cache_key = json.dumps([os.getpid(), protocol, options], sort_keys=True, default=repr)
    fs = _FILESYSTEMS.get(cache_key)
    if fs is None:
        try:
            fs = cls(**(s3_defaults(options) if is_s3 else options), skip_instance_cache=True)
        except TypeError as exc:
            raise UserError(
                f"store {url}: invalid store_options for {cls.__name__}: {exc}", field="store_options"
            ) from None
        if is_s3:
            fs.retries = 3  # s3fs's own retry loop, on top of botocore's
        _FILESYSTEMS[cache_key] = fs
    if is_s3:
        bucket, _, prefix = rest.partition("/")
        if not bucket:
            raise UserError(f"store {url}: no bucket in the URL (write s3://bucket/prefix)")
        return S3Objects(fs, bucket, prefix, url)
    root = cls._strip_protocol(url)
    return FsspecObjects(fs, root if isinstance(root, str) else url, url)


def s3_defaults(options: dict[str, Any]) -> dict[str, Any]:
    """s3fs options with bounded timeouts and retries unless the user set their own: an unreachable endpoint
    fails within seconds instead of retrying for minutes."""
    opts = dict(options)
    config = dict(opts.get("config_kwargs") or {})
    config.setdefault("connect_timeout", 5)
    config.setdefault("read_timeout", 60)
    config.setdefault("retries", {"max_attempts": 3, "mode": "standard"})
    opts["config_kwargs"] = config
    return opts


def dumps(value: Any) -> bytes:
    """Strict JSON bytes of a marker or journal entry. Keys keep their order: a manifest's meta reads back as the
    stage wrote it, as from a local store (stages may index arrays by the order of a meta mapping)."""
    return json.dumps(value, allow_nan=False).encode()


def iter_chunks(items: Iterable[tuple[str, bytes]], limit: int = 64 << 20) -> Iterator[dict[str, bytes]]:
    """Group (path, bytes) pairs into dicts of at most ~limit bytes: uploads run concurrently, memory stays bounded."""
    batch: dict[str, bytes] = {}
    size = 0
    for path, data in items:
        batch[path] = data
        size += len(data)
        if size >= limit:
            yield batch
            batch, size = {}, 0
    if batch:
        yield batch
