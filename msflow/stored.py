"""One stored output, read without zarr where that is simple: the whole array (``[...]``, what ``ArtifactView``
uses) and step-1 slices of rows decode their chunks directly, checksums checked; any other indexing, and every
other zarr attribute, go through a zarr array opened on first use.

The chunks are msflow's own (msflow.chunks: regular along the first axis, zstd, crc32c), so decoding them takes a
few lines, while zarr v3 opens a group and each array through its async machinery: about a millisecond per small
array, most of what reading a trivial stage's input cost. ``StoredArray`` holds the reading; a subclass says where
the chunk objects come from (a folder, an object store) and how zarr opens the array.
"""

from __future__ import annotations

from typing import Any


class StoredArray:
    """One output of an artifact (manifest ``entry``: shape, dtype); ``chunks``: its chunk shape when the caller
    knows it (else msflow's rule for the shape); ``checksum``: the chunks carry a crc32c (artifact format 2 on)."""

    #: stored chunks fetched at a time when reading a run of rows (each holds up to ~4 MB, msflow.chunks): an
    #: object store fetches a batch concurrently
    fetch_batch = 16

    def __init__(self, name: str, entry: dict[str, Any], chunks: list[Any] | None = None, checksum: bool = True):
        import numpy as np

        self._name = name
        self.shape = tuple(entry["shape"])
        self.dtype = np.dtype(entry["dtype"]).newbyteorder("=")  # stored little endian, read as native
        self._chunks = chunks
        self._checksum = checksum
        self._zarr: Any = None

    # ------------------------------------------------------------------ what a subclass provides
    def _fetch(self, rels: list[str]) -> dict[str, bytes | None]:
        """The chunk objects at these paths relative to the artifact's folder (None: missing)."""
        raise NotImplementedError

    def _open_zarr(self) -> Any:
        """The same array opened by zarr, read-only."""
        raise NotImplementedError

    def _where(self) -> str:
        """The artifact's folder or URL, for messages."""
        raise NotImplementedError

    # ------------------------------------------------------------------ array protocol
    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        from msflow.chunks import prod

        return prod(self.shape)

    def __len__(self) -> int:
        if not self.shape:
            raise TypeError("len() of a 0-d array")
        return int(self.shape[0])

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._where()}/{self._name}, shape={self.shape}, dtype={self.dtype})"

    @property
    def zarr(self) -> Any:
        if self._zarr is None:
            self._zarr = self._open_zarr()
        return self._zarr

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("_"):
            raise AttributeError(attr)
        return getattr(self.zarr, attr)

    @property
    def chunks(self) -> tuple[int, ...]:
        from msflow.chunks import chunk_shape

        return tuple(self._chunks) if self._chunks else chunk_shape(self.shape, self.dtype.itemsize)

    def __getitem__(self, selection: Any) -> Any:
        if _selects_everything(selection):
            return self.read()
        rows = _row_slice(selection)
        if rows is not None and self.shape:
            return self.read_rows(*rows.indices(self.shape[0])[:2])
        return self.zarr[selection]

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> Any:
        out = self.read()
        return out if dtype is None else out.astype(dtype)

    # ------------------------------------------------------------------ reading
    def read(self) -> Any:
        """The whole array: every chunk fetched (concurrently where the source can), decoded, concatenated."""
        import numpy as np

        from msflow.chunks import chunk_path, decode_chunk

        if self.size == 0:
            return np.zeros(self.shape, dtype=self.dtype)
        if self.shape:
            return self.read_rows(0, self.shape[0])
        rel = chunk_path(self._name, None, 0)
        blob = self._fetch([rel])[rel]
        if blob is None:
            raise FileNotFoundError(f"chunk {rel} of {self._where()} is missing")
        little = self.dtype.newbyteorder("<") if self.dtype.itemsize > 1 else self.dtype
        return np.array(np.frombuffer(decode_chunk(blob, self._checksum), dtype=little)[0], dtype=self.dtype)

    def read_rows(self, start: int, stop: int) -> Any:
        """Rows ``start:stop``, decoded chunk by chunk into one array: memory is the result, at most
        ``fetch_batch`` stored chunks and one decoded chunk."""
        import numpy as np

        from msflow.chunks import chunk_path, decode_chunk

        native = self.dtype
        stop = max(start, stop)
        out = np.empty((stop - start, *self.shape[1:]), dtype=native)
        if stop == start or self.size == 0:
            return out
        little = native.newbyteorder("<") if native.itemsize > 1 else native
        chunk = self.chunks
        rows = chunk[0]
        indices = list(range(start // rows, (stop - 1) // rows + 1))
        for batch in range(0, len(indices), self.fetch_batch):
            wanted = {i: chunk_path(self._name, i, len(self.shape)) for i in indices[batch : batch + self.fetch_batch]}
            blobs = self._fetch(list(wanted.values()))
            for i, rel in wanted.items():
                blob = blobs.pop(rel)
                if blob is None:
                    raise FileNotFoundError(f"chunk {rel} of {self._where()} is missing")
                block = np.frombuffer(decode_chunk(blob, self._checksum), dtype=little).reshape(chunk)
                lo, hi = max(start, i * rows), min(stop, (i + 1) * rows)
                out[lo - start : hi - start] = block[lo - i * rows : hi - i * rows]  # native byte order
        return out


class FolderArray(StoredArray):
    """An output of an artifact in a local folder (``LocalStore``; artifact format 2 on: msflow wrote its chunks)."""

    fetch_batch = 1  # files are read one after the other anyway: hold one at a time

    def __init__(self, folder: str, name: str, entry: dict[str, Any]):
        super().__init__(name, entry)
        self._folder = folder

    def _fetch(self, rels: list[str]) -> dict[str, bytes | None]:
        found: dict[str, bytes | None] = {}
        for rel in rels:
            try:
                with open(f"{self._folder}/{rel}", "rb") as fh:
                    found[rel] = fh.read()
            except FileNotFoundError:
                found[rel] = None
        return found

    def _open_zarr(self) -> Any:
        import zarr

        return zarr.open_array(self._folder, path=self._name, mode="r")

    def _where(self) -> str:
        return self._folder


def _selects_everything(selection: Any) -> bool:
    if isinstance(selection, tuple):
        return selection in ((), (Ellipsis,))
    return selection is Ellipsis or (isinstance(selection, slice) and selection == slice(None))


def _row_slice(selection: Any) -> slice | None:
    """The slice of rows a selection takes when it is a step-1 slice of whole rows (``a[i:j]``), else None."""
    if isinstance(selection, tuple):
        if not selection or not all(
            s is Ellipsis or (isinstance(s, slice) and s == slice(None)) for s in selection[1:]
        ):
            return None
        selection = selection[0]
    if isinstance(selection, slice) and selection.step in (None, 1):
        return selection
    return None
