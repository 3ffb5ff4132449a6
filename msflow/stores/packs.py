"""Small artifacts on an object store as one object: their zarr group, zipped.

On an object store every object costs a request, and most artifacts are many small objects: each output array is
its own ``zarr.json`` beside its chunk, so the default pipeline's artifacts hold 9-41 objects each, and their PUTs
were 397 of the 500 requests of a run from an empty store. An artifact whose objects add up to at most
a limit, and whose chunks were not already streamed to the store while its stage ran, is uploaded as
one uncompressed zip of exactly the objects its folder would hold (member name = path in the group, the group's
``zarr.json`` last), ``artifact.zip`` in the writer's folder; its commit marker names it (``"pack"``). The limit
is ``MSFLOW_STORE_PACK_MB`` (default 8; 0: every artifact as loose objects, as before packs existed).

It is still a zarr v3 group: zarr's ``ZipStore`` opens the downloaded file (``zarr.open_group(
zarr.storage.ZipStore("artifact.zip"))``). msflow fetches a pack once per reader (and keeps it with the objects
this process read lately), takes members from it, and checks each member's CRC-32 besides its own chunk checksums.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterable, Iterator
from typing import Any

from msflow.stores.base import env_megabytes

PACK_NAME = "artifact.zip"
DEFAULT_PACK_MB = 8.0  # a pack is read whole: a reader of one small output fetches at most this much
_EPOCH = (1980, 1, 1, 0, 0, 0)  # zip's earliest date: members carry no time, so a pack's bytes are its content's


def pack_limit() -> int:
    """The largest artifact packed, in bytes: ``MSFLOW_STORE_PACK_MB`` (default 8) megabytes; 0 packs nothing."""
    return env_megabytes("MSFLOW_STORE_PACK_MB", DEFAULT_PACK_MB)


def take_small(items: Iterable[tuple[str, bytes]], limit: int | None = None) -> tuple[list[tuple[str, bytes]], bool]:
    """The first (path, bytes) pairs while they add up to at most ``limit`` bytes (default ``pack_limit()``), and
    whether that was all of them (if not, the returned list already holds the first pair beyond the limit and the
    rest are still in ``items``, when it is an iterator)."""
    limit = pack_limit() if limit is None else limit
    taken: list[tuple[str, bytes]] = []
    size = 0
    for path, data in items:
        taken.append((path, data))
        size += len(data)
        if size > limit:
            return taken, False
    return taken, True


def make_pack(items: Iterable[tuple[str, bytes]]) -> bytes:
    """The objects as an uncompressed zip, in the given order (chunks are compressed already)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for path, data in items:
            archive.writestr(zipfile.ZipInfo(path, date_time=_EPOCH), data)
    return buffer.getvalue()


class Pack:
    """A fetched pack, read member by member. A pack that is not a zip, or a member whose CRC-32 does not match,
    raises ValueError (read damage: msflow.errors.READ_DAMAGE), so the artifact counts as corrupt."""

    def __init__(self, data: bytes, where: str):
        self.where = where
        try:
            self._zip = zipfile.ZipFile(io.BytesIO(data))
            self._names = set(self._zip.namelist())
        except (zipfile.BadZipFile, EOFError) as exc:
            raise ValueError(f"the pack {where} is not a readable zip ({exc})") from None

    def get(self, rel: str) -> bytes | None:
        """The member at ``rel`` (None when the pack has none)."""
        if rel not in self._names:
            return None
        try:
            return self._zip.read(rel)
        except (zipfile.BadZipFile, EOFError, OSError) as exc:
            raise ValueError(f"{rel} in the pack {self.where} is damaged ({exc})") from None

    def members(self) -> Iterator[tuple[str, bytes]]:
        for rel in self._zip.namelist():
            data = self.get(rel)
            assert data is not None
            yield rel, data

    def zarr_array(self, name: str) -> Any:
        """Output ``name`` opened by zarr from the pack's members (held in memory), read-only."""
        import zarr
        from zarr.core.buffer import default_buffer_prototype
        from zarr.storage import MemoryStore

        buffer = default_buffer_prototype().buffer
        members = {rel: buffer.from_bytes(data) for rel, data in self.members()}
        return zarr.open_array(MemoryStore(members, read_only=True), path=name, mode="r")
