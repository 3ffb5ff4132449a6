"""Content hashes (xxh3-128, hex): canonical JSON, numpy arrays, files (memoised by stat)."""

from __future__ import annotations

import json
import mmap
import os
from pathlib import Path
from typing import Any

import xxhash


def canonical_json(value: Any) -> str:
    """Deterministic strict JSON: sorted keys, no whitespace, NaN/Inf rejected."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def json_hash(value: Any) -> str:
    return xxhash.xxh3_128_hexdigest(canonical_json(value).encode())


def bytes_hash(data: bytes) -> str:
    return xxhash.xxh3_128_hexdigest(data)


class ArrayHasher:
    """Content hash of an array fed in blocks of its first axis, for arrays whose length is known only at the end.

    The digest covers the dtype (little-endian form), the shape and the C-order little-endian bytes: the bytes are
    streamed through xxh3-128, and dtype, shape and that digest are hashed together when the shape is known. So
    an array hashes the same whether it is hashed whole (``array_hash``) or block by block (an output sink, a
    ``verify`` that reads one chunk at a time).
    """

    def __init__(self, dtype: Any):
        import numpy as np

        dtype = np.dtype(dtype)
        self.dtype = dtype.newbyteorder("<") if dtype.byteorder == ">" else dtype
        self._bytes = xxhash.xxh3_128()

    def update(self, block: Any) -> None:
        """Add the next block (any shape; its elements follow the previous block's in C order)."""
        import numpy as np

        block = np.ascontiguousarray(np.asarray(block).astype(self.dtype, copy=False))
        self._bytes.update(block.reshape(-1).view(np.uint8).data)

    def hexdigest(self, shape: tuple[int, ...]) -> str:
        """The array's hash, once every block is in and its ``shape`` is known."""
        head = canonical_json([self.dtype.str, [int(s) for s in shape], self._bytes.hexdigest()])
        return xxhash.xxh3_128_hexdigest(head.encode())


def array_hash(arr: Any) -> str:
    """Hash of dtype, shape and C-order little-endian bytes: equal arrays hash equal however stored or streamed.

    >>> import numpy as np
    >>> array_hash(np.arange(3.0)) == array_hash(np.arange(3.0).astype(">f8"))
    True
    """
    import numpy as np

    arr = np.asarray(arr)
    hasher = ArrayHasher(arr.dtype)
    hasher.update(arr)
    return hasher.hexdigest(arr.shape)


def array_hash_v1(arr: Any) -> str:
    """The array hash of artifact format 1 (dtype and shape hashed before the bytes): verifies older artifacts."""
    import numpy as np

    arr = np.asarray(arr)
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    h = xxhash.xxh3_128()
    h.update(f"{arr.dtype.str}|{arr.shape}|".encode())
    h.update(np.ascontiguousarray(arr).reshape(-1).view(np.uint8).data)
    return h.hexdigest()


def file_hash(path: Path) -> str:
    """xxh3-128 of a file's bytes, hashed straight from the page cache through mmap (no copies)."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size == 0:
            return xxhash.xxh3_128_hexdigest(b"")
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            return xxhash.xxh3_128_hexdigest(mm)


def stat_signature(path: Path) -> str:
    """What must stay equal for a memoised file hash to stay valid: size, mtime_ns, inode."""
    st = os.stat(path)
    return f"{st.st_size}:{st.st_mtime_ns}:{st.st_ino}"


class FileHashMemo:
    """Memo of file hashes keyed by (path, size, mtime_ns, inode), persisted as JSON by the caller."""

    def __init__(self, entries: dict[str, list[str]] | None = None):
        # the caller's dict itself, even when empty: it is the memo section that gets saved
        self.entries = entries if entries is not None else {}
        #: stat signatures of every file and folder consulted: what the hashes depend on (the no-op fast path
        #: watches them)
        self.seen: dict[str, str] = {}

    def hash(self, path: Path) -> str:
        """Content hash of a file, or of a folder (its files' relative paths and hashes, hidden ones skipped)."""
        if os.path.isdir(path):
            entries = {}
            for dirpath, dirnames, files in os.walk(path):
                self.seen[dirpath] = stat_signature(Path(dirpath))
                dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
                for name in sorted(files):
                    if not name.startswith("."):
                        full = os.path.join(dirpath, name)
                        entries[os.path.relpath(full, path).replace(os.sep, "/")] = self.hash(Path(full))
            return json_hash({"folder": entries})
        key = str(path)
        sig = stat_signature(path)
        self.seen[key] = sig
        hit = self.entries.get(key)
        if hit is not None and hit[0] == sig:
            return hit[1]
        digest = file_hash(path)
        self.entries[key] = [sig, digest]
        return digest
