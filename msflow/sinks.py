"""Output sinks (frames-first outputs of unknown length, written while a stage runs) and block-wise reading.

A stage that produces a long output asks for a sink, appends blocks of frames as it computes them, and returns
the sink in its Result::

    out = self.sink("mesh", dtype="float32", row_shape=(468, 3))
    for block in iter_blocks(inputs["video_frames"], 256):
        out.append(track(block))
    return Result({"mesh": out})

In a store run each full chunk is compressed and written into the artifact's private temporary folder as soon as
it fills (so at most one chunk is held in memory), and the content hash is updated block by block: it equals the
hash of the same array returned whole. Outside a store (``msflow.testing.run_stage``, a stage called directly) a
sink keeps its blocks in memory.
"""

from __future__ import annotations

from typing import Any, Iterator, Protocol

from msflow.chunks import chunk_path, chunk_rows, encode_chunk, prod
from msflow.hashing import ArrayHasher


class ChunkTarget(Protocol):
    """Where a sink writes its chunks: a file of the artifact being written, by path relative to its group."""

    def put(self, rel: str, data: bytes) -> None: ...


class OutputSink:
    """An output of unknown length, filled by ``append(block)``; ``len(sink)`` is the number of rows so far."""

    def __init__(self, name: str, dtype: Any, row_shape: tuple[int, ...] = (), target: ChunkTarget | None = None):
        import numpy as np

        self.name = name
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(int(s) for s in row_shape)
        self.target = target
        self._rows = 0
        self._hasher = ArrayHasher(self.dtype)
        self._finished: dict[str, Any] | None = None
        self._blocks: list[Any] = []
        self._cap = chunk_rows(self.row_shape, self.dtype.itemsize)
        self._buffer: Any = None
        self._filled = 0
        self._chunks = 0
        self._finite = FiniteWatch(self.dtype)

    @property
    def streaming(self) -> bool:
        """True when chunks go to a store as they fill; False when blocks are kept in memory."""
        return self.target is not None

    @property
    def shape(self) -> tuple[int, ...]:
        return (self._rows, *self.row_shape)

    @property
    def ndim(self) -> int:
        return 1 + len(self.row_shape)

    def __len__(self) -> int:
        return self._rows

    def __repr__(self) -> str:
        return f"OutputSink({self.name!r}, shape={self.shape}, dtype={self.dtype})"

    def append(self, block: Any) -> None:
        """Add ``block`` (shape ``(m, *row_shape)``, m >= 0) after the rows appended so far."""
        import numpy as np

        if self._finished is not None:
            raise RuntimeError(f"output sink '{self.name}' is finished: nothing can be appended")
        block = np.asarray(block)
        if block.ndim != self.ndim or block.shape[1:] != self.row_shape:
            raise ValueError(
                f"output sink '{self.name}': block of shape {block.shape}, expected (m, {', '.join(map(str, self.row_shape))})"
                if self.row_shape
                else f"output sink '{self.name}': block of shape {block.shape}, expected (m,)"
            )
        if not np.can_cast(block.dtype, self.dtype, "same_kind"):
            raise TypeError(f"output sink '{self.name}': cannot store {block.dtype} blocks as {self.dtype}")
        block = block.astype(self.dtype, copy=False)
        self._hasher.update(block)
        self._finite.update(block)
        self._rows += block.shape[0]
        if self.target is None:
            self._blocks.append(block.copy())  # the caller may reuse its buffer for the next block
        elif prod(self.row_shape):
            self._fill(block)

    def _fill(self, block: Any) -> None:
        """Copy rows into the chunk buffer, writing each chunk as it fills. The buffer grows by doubling up to a
        chunk, so a short output never allocates a whole chunk."""
        import numpy as np

        pos = 0
        while pos < block.shape[0]:
            want = min(self._cap, self._filled + block.shape[0] - pos)
            if self._buffer is None or self._buffer.shape[0] < want:
                size = min(self._cap, max(want, 2 * (0 if self._buffer is None else self._buffer.shape[0])))
                grown = np.empty((size, *self.row_shape), dtype=self.dtype)
                if self._filled:
                    grown[: self._filled] = self._buffer[: self._filled]
                self._buffer = grown
            take = min(self._cap - self._filled, block.shape[0] - pos)
            self._buffer[self._filled : self._filled + take] = block[pos : pos + take]
            self._filled += take
            pos += take
            if self._filled == self._cap:
                self._flush(self._cap)

    def _flush(self, stored_rows: int) -> None:
        assert self.target is not None
        data = encode_chunk(self._buffer[: self._filled], stored_rows)
        self.target.put(chunk_path(self.name, self._chunks, self.ndim), data)
        self._chunks += 1
        self._filled = 0

    def finish(self) -> dict[str, Any]:
        """Write the last chunk; return the manifest entry (hash, shape, dtype). Idempotent."""
        if self._finished is None:
            if self._filled:
                # one short chunk holds exactly the rows (as a whole array of that length is chunked); later
                # edge chunks are padded to full size
                self._flush(self._cap if self._chunks else self._filled)
            self._buffer = None
            self._finished = {
                "hash": self._hasher.hexdigest(self.shape),
                "shape": list(self.shape),
                "dtype": str(self.dtype),
            }
        return dict(self._finished)

    def nonfinite_warning(self) -> str | None:
        """The run warning when the rows appended hold values and none is finite (``FiniteWatch``)."""
        return self._finite.warning(self.name, self._rows * prod(self.row_shape))

    def to_array(self) -> Any:
        """The whole array (in-memory sinks only)."""
        import numpy as np

        if self.target is not None:
            raise RuntimeError(f"output sink '{self.name}' streams to a store: read the artifact instead")
        if not self._blocks:
            return np.zeros(self.shape, dtype=self.dtype)
        return np.concatenate(self._blocks) if len(self._blocks) > 1 else self._blocks[0]


#: elements looked at in one step while no finite value has been seen (bounds the temporary masks)
SCAN_STEP = 1 << 20


class FiniteWatch:
    """Whether a float (or complex) output has any finite value, watched block by block as it is produced. An
    output with none (all NaN, or NaN and Inf) is almost always a bug or data the stage could not use, so msflow
    warns instead of storing it silently. Once a finite value is seen nothing more is looked at, and the first
    element of a block usually settles it: an ordinary output costs one element per block, never a re-read."""

    def __init__(self, dtype: Any):
        import numpy as np

        self.watched = np.dtype(dtype).kind in "fc"
        self.finite_seen = False
        self.nan_only = True  #: every value seen so far (while none was finite) is NaN

    def update(self, block: Any) -> None:
        import numpy as np

        if not self.watched or self.finite_seen or block.size == 0:
            return
        if np.isfinite(block.flat[0]):
            self.finite_seen = True
            return
        flat = block.reshape(-1)
        for start in range(0, flat.size, SCAN_STEP):
            part = flat[start : start + SCAN_STEP]
            if np.isfinite(part).any():
                self.finite_seen = True
                return
            self.nan_only = self.nan_only and bool(np.isnan(part).all())

    def warning(self, name: str, size: int) -> str | None:
        """The run warning for output ``name`` of ``size`` values when none is finite (an empty one has none).

        >>> import numpy as np
        >>> watch = FiniteWatch(np.float32)
        >>> watch.update(np.full(3, np.nan, np.float32)); watch.warning("y", 3)
        "output 'y' is all NaN (3 values)"
        >>> watch.update(np.array([np.inf, 1.0])); watch.warning("y", 5) is None
        True
        """
        if not self.watched or self.finite_seen or not size:
            return None
        what = "NaN" if self.nan_only else "NaN or Inf"
        return f"output '{name}' is all {what} ({size:,} values)"


def nonfinite_warnings(arrays: dict[str, Any]) -> list[str]:
    """The run warnings of a stage's validated outputs (numpy arrays or finished sinks) that hold values, none
    of them finite; a sink watched its blocks as they were appended."""
    found = []
    for name, value in arrays.items():
        if isinstance(value, OutputSink):
            message = value.nonfinite_warning()
        else:
            watch = FiniteWatch(value.dtype)
            watch.update(value)
            message = watch.warning(name, value.size)
        if message:
            found.append(message)
    return found


def iter_blocks(array: Any, rows: int | None = None) -> Iterator[Any]:
    """Consecutive blocks of ``rows`` rows (default: the stored chunk length) of a frames-first array, as numpy.

    Works on numpy arrays, zarr arrays and lazy inputs (``Input.array(lazy=True)``, ``view.lazy(name)``), so a
    long take is processed with one block in memory at a time.

    >>> import numpy as np
    >>> [b.tolist() for b in iter_blocks(np.arange(5), 2)]
    [[0, 1], [2, 3], [4]]
    """
    import numpy as np

    shape = tuple(array.shape)
    if not shape:
        raise ValueError("iter_blocks needs an array with a first (frames) axis")
    if rows is None:
        chunks = getattr(array, "chunks", None)
        rows = int(chunks[0]) if chunks else chunk_rows(shape[1:], np.dtype(array.dtype).itemsize)
    if rows < 1:
        raise ValueError(f"iter_blocks: rows must be at least 1, got {rows}")
    for start in range(0, shape[0], rows):
        yield np.asarray(array[start : start + rows])
