"""Atomic file writes: a file appears complete or not at all (temporary sibling, then one ``os.replace``).

The one idiom for every file msflow writes outside artifacts: memo, run records, ``pipeline.lock``, exports and
published files. A failed write removes its temporary file.
"""

from __future__ import annotations

import contextlib
import json
import os
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any


def temporary_sibling(path: Path) -> Path:
    """A hidden, unique name in ``path``'s folder (same file system, so the final rename is atomic)."""
    return path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[IO[bytes]]:
    """Open a temporary sibling of ``path`` for binary writing; on success it replaces ``path`` in one rename,
    on failure it is removed (nothing is left behind, ``path`` is untouched)."""
    path = Path(path)
    tmp = temporary_sibling(path)
    try:
        with open(tmp, "wb") as fh:
            yield fh
        os.replace(tmp, path)
    except OSError as exc:
        if exc.filename is None:  # a failed write or close names no file: name the one being written
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` (text is UTF-8 encoded) to ``path`` atomically."""
    with atomic_file(path) as fh:
        fh.write(data.encode("utf-8") if isinstance(data, str) else data)


def write_json_atomic(path: str | Path, value: Any, indent: int | None = None) -> None:
    """Strict JSON (NaN rejected) written atomically; indented records have sorted keys."""
    write_atomic(path, json.dumps(value, indent=indent, sort_keys=indent is not None, allow_nan=False))


def write_with(path: str | Path, writer: Callable[[IO[bytes]], object]) -> None:
    """Call ``writer(binary file)`` to fill ``path`` atomically (for writers that take a file, e.g. numpy.save)."""
    with atomic_file(path) as fh:
        writer(fh)
