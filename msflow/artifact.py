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
from msflow.hashing import ArrayHasher, array_hash, array_hash_v1, json_hash
from msflow.sinks import OutputSink, iter_blocks

FORMAT = 2  # 2: incremental array hash (hashing.ArrayHasher), crc32c on every chunk


class ArtifactView:
    """Read access to an artifact: ``view["name"]`` is numpy, ``view.lazy("name")`` the stored (zarr) array."""

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
            import numpy as np

            if name not in self._arrays:
                raise KeyError(f"artifact has no output '{name}'; it has {sorted(self._arrays)}")
            self._loaded[name] = np.asarray(self._arrays[name][...])
        return self._loaded[name]

    def get(self, name: str, default: Any = None) -> Any:
        return self[name] if name in self._arrays else default

    def lazy(self, name: str) -> Any:
        """The stored array, unread: slice it (``iter_blocks``) to read blocks of frames."""
        return self._arrays[name]

    def bytes(self, name: str) -> bytes:
        data: bytes = self[name].tobytes()
        return data

    def __repr__(self) -> str:
        return f"ArtifactView({', '.join(self.names)})"


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
    """The manifest alone, without importing zarr."""
    with open(Path(path) / "zarr.json", "rb") as fh:
        manifest: dict[str, Any] = json.load(fh)["attributes"]["msflow"]
    return manifest


def read_artifact(path: Path, key: str | None = None) -> ArtifactView:
    import zarr

    manifest = read_manifest(path)
    group = zarr.open_group(str(path), mode="r")
    arrays = {name: group[name] for name in manifest["outputs"]}
    return ArtifactView(arrays, manifest.get("meta", {}), manifest.get("metrics", {}), key=key, manifest=manifest)


def verify_artifact(path: Path) -> list[str]:
    """Recompute every content hash of an artifact; return a list of problems (empty when intact)."""
    try:
        manifest = read_manifest(path)
    except Exception as exc:  # unreadable zarr.json is itself the finding
        return [f"manifest unreadable: {exc}"]
    try:
        view = read_artifact(path)
    except Exception as exc:
        return [f"unreadable: {type(exc).__name__}: {exc}"]
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
            except Exception as exc:
                problems.append(f"output '{name}': unreadable ({type(exc).__name__}: {exc})")
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
