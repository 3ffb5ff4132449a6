"""Artifact stores: ``open_store`` picks the backend for a location; ``Store`` is the contract both implement.

- ``msflow.stores.local``: a folder (``.msflow`` by default) on a local or shared POSIX file system;
- ``msflow.stores.remote``: an object store (``s3://bucket/prefix`` or any fsspec URL), with
  ``msflow.stores.objects`` (object primitives, S3 and fsspec) and ``msflow.stores.leases`` (per-key leases).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from msflow.stores.base import ArtifactWriter, Store


def open_store(location: str, options: dict[str, Any] | None = None, cache_dir: str | Path | None = None) -> Store:
    """A store for a path or URL: ``file://`` and plain paths are local folders, other URLs (``s3://`` ...) object
    stores through fsspec. ``options`` are fsspec storage options; ``cache_dir`` holds the machine-local memo of
    an object store (file stat signatures mean nothing on another machine)."""
    if location.startswith("file://"):
        location = location[len("file://") :]
    elif "://" in location:
        from msflow.stores.remote import open_remote_store

        return open_remote_store(location, options or {}, cache_dir)
    from msflow.stores.local import LocalStore

    return LocalStore(location)


__all__ = ["ArtifactWriter", "Store", "open_store"]
