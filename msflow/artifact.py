"""One artifact = one zarr v3 group: chunked zstd arrays plus a strict-JSON manifest in its attributes.

The manifest (``attributes["msflow"]``) records every output's content hash, shape and dtype, the stage's
metadata and metrics, and the artifact's content hash. It is plain JSON in ``zarr.json``, so the no-op path reads
it with ``json`` alone; zarr is imported only to read or write arrays.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from msflow.chunks import array_metadata, chunk_path, encode_chunk
from msflow.errors import READ_DAMAGE, CorruptArtifact
from msflow.hashing import ArrayHasher, array_hash, array_hash_v1, json_hash
from msflow.sinks import OutputSink, iter_blocks

FORMAT = 2  # 2: incremental array hash (hashing.ArrayHasher), crc32c on every chunk


class ArtifactView:
    """Read access to an artifact: ``view["name"]`` is numpy, ``view.lazy("name")`` the stored array, unread.

    Reads are checked: a chunk whose checksum does not match, or that is missing, raises ``CorruptArtifact``
    naming the artifact, never a wrong value.
    """

    def __init__(
        self,
        arrays: Mapping[str, Any],
        meta: dict[str, Any],
        metrics: dict[str, Any],
        key: str | None = None,
        manifest: dict[str, Any] | None = None,
    ):
        self._arrays = dict(arrays)
        self._loaded: dict[str, Any] = {}
        self.meta = meta
        self.metrics = metrics
        self.key = key
        self.manifest = manifest or {}

    @property
    def warnings(self) -> list[str]:
        """The warnings the stage attached to this result (``Result.warnings``)."""
        return list(self.manifest.get("warnings", []))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._arrays)

    def __contains__(self, name: object) -> bool:
        return name in self._arrays

    def __getitem__(self, name: str) -> Any:
        if name not in self._loaded:
            if name not in self._arrays:
                raise KeyError(f"artifact has no output '{name}'; it has {sorted(self._arrays)}")
            self._loaded[name] = self.lazy(name)[...]
        return self._loaded[name]

    def get(self, name: str, default: Any = None) -> Any:
        return self[name] if name in self._arrays else default

    def lazy(self, name: str) -> CheckedArray:
        """The stored array, unread: slice it (``iter_blocks``) to read blocks of frames."""
        return CheckedArray(self._arrays[name], self.key, name)

    def bytes(self, name: str) -> bytes:
        data: bytes = self[name].tobytes()
        return data

    def __repr__(self) -> str:
        key = f"{self.key[:12]}: " if self.key else ""
        return f"ArtifactView({key}{', '.join(self.names)})"


class CheckedArray:
    """A stored array (zarr, remote, numpy) whose reads turn damage into ``CorruptArtifact``; otherwise it behaves
    as the array it wraps (``shape``, ``dtype``, ``chunks``, slicing, ``np.asarray``)."""

    def __init__(self, array: Any, key: str | None, name: str):
        self._array = array
        self._key = key
        self._name = name

    def __getitem__(self, selection: Any) -> Any:
        import numpy as np

        try:
            return np.asarray(self._array[selection])
        except READ_DAMAGE as exc:
            raise CorruptArtifact(self._key, f"output '{self._name}': {type(exc).__name__}: {exc}") from None

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> Any:
        out = self[...]
        return out if dtype is None else out.astype(dtype)

    def __len__(self) -> int:
        return len(self._array)

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("_"):
            raise AttributeError(attr)
        return getattr(self._array, attr)

    def __repr__(self) -> str:
        return f"CheckedArray({self._name}, shape={tuple(self._array.shape)}, dtype={self._array.dtype})"


def meta_digest(meta: dict[str, Any], metrics: dict[str, Any], warnings: list[str] | None = None) -> str:
    """Hash of the JSON part of an artifact (warnings enter only when there are some: older hashes hold)."""
    content: dict[str, Any] = {"meta": meta, "metrics": metrics}
    if warnings:
        content["warnings"] = warnings
    return json_hash(content)


def output_entry(value: Any) -> dict[str, Any]:
    """Manifest entry of one output: content hash, shape, dtype (of an array, or of a finished output sink)."""
    if isinstance(value, OutputSink):
        return value.finish()
    return {"hash": array_hash(value), "shape": list(value.shape), "dtype": str(value.dtype)}


def build_manifest(
    arrays: Mapping[str, Any],
    meta: dict[str, Any],
    metrics: dict[str, Any],
    file_suffixes: Mapping[str, str | None] | None = None,
    warnings: list[str] | None = None,
) -> dict[str, Any]:
    """Content hashes of arrays and metadata; ``content_hash`` identifies the artifact's content."""
    outputs = {}
    for name, arr in arrays.items():
        entry = output_entry(arr)
        suffix = (file_suffixes or {}).get(name)
        if suffix:
            entry["file_suffix"] = suffix
        outputs[name] = entry
    meta_hash = meta_digest(meta, metrics, warnings)
    content = json_hash({"outputs": {k: v["hash"] for k, v in sorted(outputs.items())}, "meta": meta_hash})
    manifest = {
        "format": FORMAT,
        "outputs": outputs,
        "meta": meta,
        "metrics": metrics,
        "meta_hash": meta_hash,
        "content_hash": content,
    }
    if warnings:
        manifest["warnings"] = list(warnings)
    return manifest


def encode_artifact(arrays: Mapping[str, Any], manifest: dict[str, Any]) -> Iterator[tuple[str, bytes]]:
    """Yield (relative path, bytes) of a complete zarr v3 group holding ``arrays``, manifest in its attributes.

    Written directly rather than through zarr's async machinery, which costs ~20 ms per small artifact; the
    result is plain zarr v3 that zarr (and any v3 reader) opens. Output sinks wrote their chunks already: only
    their array metadata is yielded here. The group's zarr.json comes last, so a reader that finds it may assume
    everything else is there.
    """
    for name, arr in arrays.items():
        entry = manifest["outputs"][name]
        meta = array_metadata(tuple(entry["shape"]), entry["dtype"])
        yield f"{name}/zarr.json", json.dumps(meta, allow_nan=False).encode()
        if isinstance(arr, OutputSink) or arr.size == 0:
            continue
        if arr.ndim == 0:
            yield chunk_path(name, None, 0), encode_chunk(arr)
            continue
        step = meta["chunk_grid"]["configuration"]["chunk_shape"][0]
        for index, start in enumerate(range(0, arr.shape[0], step)):
            yield chunk_path(name, index, arr.ndim), encode_chunk(arr[start : start + step], step)
    group = {"attributes": {"msflow": manifest}, "zarr_format": 3, "node_type": "group"}
    yield "zarr.json", json.dumps(group, allow_nan=False).encode()


def settle_output(value: Any) -> Any:
    """An output as it is written: a streaming sink stays (its chunks are stored), an in-memory sink becomes its
    array, anything else a C-order numpy array."""
    import numpy as np

    if isinstance(value, OutputSink):
        return value if value.streaming else value.to_array()
    return np.asarray(value, order="C")


def prepare_manifest(
    arrays: Mapping[str, Any], manifest_extra: dict[str, Any], file_suffixes: Mapping[str, str | None] | None = None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(outputs as C-order numpy arrays or finished sinks, manifest); ``manifest_extra`` holds meta, metrics,
    warnings and any other manifest fields (key, stage, ...)."""

    arrays = {k: settle_output(v) for k, v in arrays.items()}
    manifest = build_manifest(
        arrays,
        manifest_extra.get("meta", {}),
        manifest_extra.get("metrics", {}),
        file_suffixes,
        manifest_extra.get("warnings"),
    )
    manifest.update({k: v for k, v in manifest_extra.items() if k not in ("meta", "metrics", "warnings")})
    return arrays, manifest


def write_files(path: Path, files: Iterable[tuple[str, bytes]]) -> None:
    """Write (relative path, bytes) pairs under ``path``, creating folders as needed."""
    made: set[Path] = set()
    for rel, data in files:
        target = path / rel
        if target.parent not in made:
            target.parent.mkdir(parents=True, exist_ok=True)
            made.add(target.parent)
        with open(target, "wb") as fh:
            fh.write(data)


def write_artifact(
    path: Path,
    arrays: Mapping[str, Any],
    manifest_extra: dict[str, Any],
    file_suffixes: Mapping[str, str | None] | None = None,
) -> dict[str, Any]:
    """Write a new zarr group at ``path`` (which must not exist) and return its manifest."""
    arrays, manifest = prepare_manifest(arrays, manifest_extra, file_suffixes)
    path = Path(path)
    path.mkdir(parents=True, exist_ok=False)
    write_files(path, encode_artifact(arrays, manifest))
    return manifest


def read_manifest(path: Path) -> dict[str, Any]:
    """The manifest alone, without importing zarr; ``CorruptArtifact`` when it is missing, truncated or malformed."""
    path = Path(path)
    try:
        with open(path / "zarr.json", "rb") as fh:
            manifest = json.load(fh)["attributes"]["msflow"]
    except FileNotFoundError:
        raise CorruptArtifact(path.name, "its manifest (zarr.json) is missing") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise CorruptArtifact(
            path.name, f"its manifest (zarr.json) is unreadable: {type(exc).__name__}: {exc}"
        ) from None
    check_manifest(path.name, manifest)
    checked: dict[str, Any] = manifest
    return checked


def check_manifest(key: str | None, manifest: Any) -> None:
    """Raise CorruptArtifact unless ``manifest`` has the fields readers rely on."""
    try:
        outputs = manifest["outputs"]
        ok = isinstance(outputs, dict) and all(
            isinstance(e["hash"], str) and isinstance(e["shape"], list) and isinstance(e["dtype"], str)
            for e in outputs.values()
        )
        ok = ok and isinstance(manifest["content_hash"], str)
    except (KeyError, TypeError):
        ok = False
    if not ok:
        raise CorruptArtifact(key, "its manifest lacks output hashes, shapes or dtypes")


def missing_chunks(path: Path, manifest: dict[str, Any]) -> list[str]:
    """Chunk files an artifact's outputs need that are not there (zarr would read them as zeros)."""
    import os

    from msflow.chunks import chunk_shape, prod

    missing = []
    for name, entry in manifest["outputs"].items():
        shape = tuple(entry["shape"])
        if not prod(shape):
            continue
        if not shape:
            paths = [chunk_path(name, None, 0)]
        else:
            import numpy as np

            rows = chunk_shape(shape, np.dtype(entry["dtype"]).itemsize)[0]
            paths = [chunk_path(name, i, len(shape)) for i in range(-(-shape[0] // rows))]
        missing += [p for p in paths if not os.path.isfile(path / p)]
    return missing


def read_artifact(path: Path, key: str | None = None, through_zarr: bool = False) -> ArtifactView:
    """Open a local artifact: its manifest is checked and every chunk must be present; chunk checksums are checked
    as they are read. ``CorruptArtifact`` otherwise. msflow's own chunks (format 2 on) are read directly
    (msflow.stored), anything else, or everything with ``through_zarr``, through zarr."""
    from msflow.stored import FolderArray

    path = Path(path)
    key = key or path.name
    manifest = read_manifest(path)
    missing = missing_chunks(path, manifest)
    if missing:
        raise CorruptArtifact(key, f"{len(missing)} chunk file(s) missing, e.g. {missing[0]}")
    if manifest.get("format", 1) >= FORMAT and not through_zarr:
        arrays: dict[str, Any] = {
            name: FolderArray(str(path), name, entry) for name, entry in manifest["outputs"].items()
        }
    else:
        arrays = zarr_arrays(path, key, manifest)
    return ArtifactView(arrays, manifest.get("meta", {}), manifest.get("metrics", {}), key=key, manifest=manifest)


def zarr_arrays(path: Path, key: str, manifest: dict[str, Any]) -> dict[str, Any]:
    """The artifact's outputs opened by zarr (which also checks every array's own zarr.json)."""
    import zarr

    try:
        group = zarr.open_group(str(path), mode="r")
        return {name: group[name] for name in manifest["outputs"]}
    except (*READ_DAMAGE, TypeError) as exc:
        raise CorruptArtifact(key, f"its arrays cannot be opened: {type(exc).__name__}: {exc}") from None


def verify_artifact(path: Path) -> list[str]:
    """Recompute every content hash of an artifact, reading it through zarr (so the folder stays a zarr group any
    zarr reader opens); return a list of problems (empty when intact)."""
    try:
        manifest = read_manifest(path)
        view = read_artifact(path, through_zarr=True)
    except CorruptArtifact as exc:
        return [exc.problem]
    return check_contents(manifest, view.lazy)


def stored_hash(manifest: dict[str, Any], array: Any) -> str:
    """Content hash of a stored output read block by block (bounded memory), by the manifest format's rule."""
    if manifest.get("format", 1) < 2:
        return array_hash_v1(array[...])
    hasher = ArrayHasher(array.dtype)
    if not array.shape:
        hasher.update(array[...])
    else:
        for block in iter_blocks(array):
            hasher.update(block)
    return hasher.hexdigest(tuple(array.shape))


def check_contents(manifest: dict[str, Any], lazy: Callable[[str], Any]) -> list[str]:
    """Problems found recomputing the content hashes recorded in ``manifest``; ``lazy(name)`` opens an output as
    a sliceable array (a zarr array, a remote array, numpy), read here one chunk at a time."""
    problems = []
    try:
        for name, entry in manifest["outputs"].items():
            try:
                got = stored_hash(manifest, lazy(name))
            except Exception as exc:  # a CorruptArtifact's problem, without the advice its message adds
                detail = exc.problem if isinstance(exc, CorruptArtifact) else f"{type(exc).__name__}: {exc}"
                problems.append(f"output '{name}': unreadable ({detail.removeprefix(f'output {name!r}: ')})")
                continue
            if got != entry["hash"]:
                problems.append(f"output '{name}': content hash {got} != recorded {entry['hash']}")
        if meta_digest(manifest.get("meta", {}), manifest.get("metrics", {}), manifest.get("warnings")) != manifest.get(
            "meta_hash"
        ):
            problems.append("metadata: hash differs from recorded")
        content = json_hash(
            {
                "outputs": {k: v["hash"] for k, v in sorted(manifest["outputs"].items())},
                "meta": manifest.get("meta_hash"),
            }
        )
        if content != manifest.get("content_hash"):
            problems.append("manifest: content hash differs from recorded")
    except Exception as exc:
        problems.append(f"unreadable: {type(exc).__name__}: {exc}")
    return problems
