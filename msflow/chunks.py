"""The stored form of one array: zarr v3 chunks along the first axis, zstd-compressed, each with a crc32c.

Shared by whole-array writes (msflow.artifact), output sinks (msflow.sinks) and the object-store reader
(msflow.stores.remote). Chunks carry zarr v3's ``crc32c`` codec: zarr checks it on every read, and so does
``decode_chunk``, so a flipped byte is an error, never a wrong value.
"""

from __future__ import annotations

from typing import Any

CHUNK_BYTES = 4 << 20


def chunk_shape(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    """Chunk along the first axis only, about CHUNK_BYTES each: frames are read in runs."""
    if not shape:
        return ()
    return (max(1, min(shape[0], chunk_rows(shape[1:], itemsize))),) + tuple(max(1, s) for s in shape[1:])


def chunk_rows(row_shape: tuple[int, ...], itemsize: int) -> int:
    """Rows of a full chunk: as many as fit in CHUNK_BYTES (at least one)."""
    return max(1, CHUNK_BYTES // (itemsize * max(1, prod(row_shape))))


def prod(values: Any) -> int:
    out = 1
    for v in values:
        out *= int(v)
    return out


ZSTD_LEVEL = 3


def fill_value(dtype: Any) -> Any:
    """The zarr fill value msflow writes for a dtype (edge chunks are padded with it)."""
    import numpy as np

    kind = np.dtype(dtype).kind
    return False if kind == "b" else [0.0, 0.0] if kind == "c" else 0.0 if kind == "f" else 0


def array_metadata(shape: tuple[int, ...], dtype: Any) -> dict[str, Any]:
    """zarr v3 array metadata: regular chunks along the first axis; codecs bytes (little endian), zstd, then a
    crc32c checksum of every stored chunk, which zarr (and msflow's own reader) checks on every read."""
    import numpy as np

    dtype = np.dtype(dtype)
    bytes_codec: dict[str, Any] = {"name": "bytes"}
    if dtype.itemsize > 1:
        bytes_codec["configuration"] = {"endian": "little"}
    return {
        "shape": [int(s) for s in shape],
        "data_type": dtype.name,
        "chunk_grid": {
            "name": "regular",
            "configuration": {"chunk_shape": list(chunk_shape(tuple(shape), dtype.itemsize))},
        },
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": fill_value(dtype),
        "codecs": [
            bytes_codec,
            {"name": "zstd", "configuration": {"level": ZSTD_LEVEL, "checksum": False}},
            {"name": "crc32c"},
        ],
        "attributes": {},
        "zarr_format": 3,
        "node_type": "array",
        "storage_transformers": [],
    }


def chunk_path(name: str, index: int | None, ndim: int) -> str:
    """Relative path of a chunk of output ``name`` (``index`` None: the single chunk of a 0-d array)."""
    if index is None:
        return f"{name}/c"
    return f"{name}/c/{index}" + "/0" * (ndim - 1)


def encode_chunk(block: Any, rows: int | None = None) -> bytes:
    """One stored chunk: ``block`` padded to ``rows`` rows with the fill value (zarr stores edge chunks at full
    size), little-endian bytes, zstd, and the crc32c of the compressed bytes appended (zarr v3's crc32c codec)."""
    import google_crc32c
    import numpy as np
    from numcodecs import Zstd

    block = np.asarray(block)
    if block.dtype.byteorder == ">":
        block = block.astype(block.dtype.newbyteorder("<"))
    if rows is not None and block.shape[0] < rows:
        padded = np.zeros((rows,) + block.shape[1:], dtype=block.dtype)
        padded[: block.shape[0]] = block
        block = padded
    compressed = Zstd(level=ZSTD_LEVEL).encode(np.ascontiguousarray(block))
    return b"".join((compressed, google_crc32c.value(compressed).to_bytes(4, "little")))


class CorruptChunk(ValueError):
    """A stored chunk whose checksum does not match its bytes (or that is too short to hold one)."""


def decode_chunk(data: bytes, checksum: bool = True) -> bytes:
    """The raw (little-endian) bytes of a stored chunk; raises CorruptChunk when its crc32c does not match."""
    import google_crc32c
    from numcodecs import Zstd

    if checksum:
        if len(data) < 4:
            raise CorruptChunk("chunk too short to hold its checksum")
        payload, stored = data[:-4], int.from_bytes(data[-4:], "little")
        if google_crc32c.value(payload) != stored:
            raise CorruptChunk("chunk checksum mismatch (crc32c)")
        data = payload
    return bytes(Zstd().decode(data))
