"""One artifact = one zarr v3 group: chunked zstd arrays plus a strict-JSON manifest in its attributes.

The manifest (``attributes["msflow"]``) records every output's content hash, shape and dtype, the stage's
metadata and metrics, and the artifact's content hash. It is plain JSON in ``zarr.json``, so the no-op path reads
it with ``json`` alone; zarr is imported only to read or write arrays.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from msflow.hashing import array_hash, json_hash

FORMAT = 1
CHUNK_BYTES = 4 << 20


class ArtifactView:
    """Read access to an artifact: ``view["name"]`` is numpy, ``view.lazy("name")`` the stored (zarr) array."""

    def __init__(
        self, arrays: Mapping[str, Any], meta: dict, metrics: dict, key: str | None = None, manifest: dict | None = None
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

    def __getitem__(self, name: str):
        if name not in self._loaded:
            import numpy as np

            if name not in self._arrays:
                raise KeyError(f"artifact has no output '{name}'; it has {sorted(self._arrays)}")
            self._loaded[name] = np.asarray(self._arrays[name][...])
        return self._loaded[name]

    def get(self, name: str, default=None):
        return self[name] if name in self._arrays else default

    def lazy(self, name: str):
        return self._arrays[name]

    def bytes(self, name: str) -> bytes:
        return self[name].tobytes()

    def __repr__(self) -> str:
        return f"ArtifactView({', '.join(self.names)})"


def chunk_shape(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    """Chunk along the first axis only, about CHUNK_BYTES each: frames are read in runs."""
    if not shape:
        return ()
    row = itemsize * max(1, int(_prod(shape[1:])))
    return (max(1, min(shape[0], CHUNK_BYTES // row)),) + tuple(max(1, s) for s in shape[1:])


def _prod(values) -> int:
    out = 1
    for v in values:
        out *= v
    return out


def meta_digest(meta: dict, metrics: dict, warnings: list[str] | None = None) -> str:
    """Hash of the JSON part of an artifact (warnings enter only when there are some: older hashes hold)."""
    content: dict[str, Any] = {"meta": meta, "metrics": metrics}
    if warnings:
        content["warnings"] = warnings
    return json_hash(content)


def build_manifest(
    arrays: Mapping[str, Any],
    meta: dict,
    metrics: dict,
    file_suffixes: Mapping[str, str | None] | None = None,
    warnings: list[str] | None = None,
) -> dict:
    """Content hashes of arrays and metadata; ``content_hash`` identifies the artifact's content."""
    outputs = {}
    for name, arr in arrays.items():
        entry = {"hash": array_hash(arr), "shape": list(arr.shape), "dtype": str(arr.dtype)}
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


ZSTD_LEVEL = 3


def array_metadata(arr) -> dict:
    """zarr v3 array metadata: regular chunks along the first axis, bytes (little endian) + zstd codecs."""
    bytes_codec = {"name": "bytes"}
    if arr.dtype.itemsize > 1:
        bytes_codec["configuration"] = {"endian": "little"}
    fill = False if arr.dtype.kind == "b" else 0.0 if arr.dtype.kind in "fc" else 0
    if arr.dtype.kind == "c":
        fill = [0.0, 0.0]
    return {
        "shape": list(arr.shape),
        "data_type": arr.dtype.name,
        "chunk_grid": {
            "name": "regular",
            "configuration": {"chunk_shape": list(chunk_shape(arr.shape, arr.dtype.itemsize))},
        },
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": fill,
        "codecs": [bytes_codec, {"name": "zstd", "configuration": {"level": ZSTD_LEVEL, "checksum": False}}],
        "attributes": {},
        "zarr_format": 3,
        "node_type": "array",
        "storage_transformers": [],
    }


def encode_artifact(arrays: Mapping[str, Any], manifest: dict):
    """Yield (relative path, bytes) of a complete zarr v3 group holding ``arrays``, manifest in its attributes.

    Written directly rather than through zarr's async machinery, which costs ~20 ms per small artifact; the
    result is plain zarr v3 that zarr (and any v3 reader) opens. The group's zarr.json comes last, so a reader
    that finds it may assume everything else is there.
    """
    import numpy as np
    from numcodecs import Zstd

    codec = Zstd(level=ZSTD_LEVEL)
    for name, arr in arrays.items():
        meta = array_metadata(arr)
        yield f"{name}/zarr.json", json.dumps(meta, allow_nan=False).encode()
        if arr.size == 0:
            continue
        little = arr.astype(arr.dtype.newbyteorder("<"), copy=False) if arr.dtype.byteorder == ">" else arr
        if arr.ndim == 0:
            yield f"{name}/c", codec.encode(np.ascontiguousarray(little).tobytes())
            continue
        step = meta["chunk_grid"]["configuration"]["chunk_shape"][0]
        rest = "/0" * (arr.ndim - 1)
        for index, start in enumerate(range(0, arr.shape[0], step)):
            block = little[start : start + step]
            if block.shape[0] < step:  # zarr stores edge chunks at full chunk size, padded with the fill value
                padded = np.zeros((step,) + block.shape[1:], dtype=block.dtype)
                padded[: block.shape[0]] = block
                block = padded
            yield f"{name}/c/{index}{rest}", codec.encode(np.ascontiguousarray(block).tobytes())
    group = {"attributes": {"msflow": manifest}, "zarr_format": 3, "node_type": "group"}
    yield "zarr.json", json.dumps(group, allow_nan=False).encode()


def prepare_manifest(
    arrays: Mapping[str, Any], manifest_extra: dict, file_suffixes: Mapping[str, str | None] | None = None
) -> tuple[dict, dict]:
    import numpy as np

    arrays = {k: np.asarray(v, order="C") for k, v in arrays.items()}
    manifest = build_manifest(
        arrays,
        manifest_extra.get("meta", {}),
        manifest_extra.get("metrics", {}),
        file_suffixes,
        manifest_extra.get("warnings"),
    )
    manifest.update({k: v for k, v in manifest_extra.items() if k not in ("meta", "metrics", "warnings")})
    return arrays, manifest


def write_artifact(
    path: Path, arrays: Mapping[str, Any], manifest_extra: dict, file_suffixes: Mapping[str, str | None] | None = None
) -> dict:
    """Write a new zarr group at ``path`` (which must not exist) and return its manifest."""
    arrays, manifest = prepare_manifest(arrays, manifest_extra, file_suffixes)
    path = Path(path)
    path.mkdir(parents=True, exist_ok=False)
    made = {path}
    for rel, data in encode_artifact(arrays, manifest):
        target = path / rel
        if target.parent not in made:
            target.parent.mkdir(parents=True, exist_ok=True)
            made.add(target.parent)
        with open(target, "wb") as fh:
            fh.write(data)
    return manifest


def read_manifest(path: Path) -> dict:
    """The manifest alone, without importing zarr."""
    with open(Path(path) / "zarr.json", "rb") as fh:
        return json.load(fh)["attributes"]["msflow"]


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
    return check_contents(manifest, view.__getitem__)


def check_contents(manifest: dict, load) -> list[str]:
    """Problems found recomputing the content hashes recorded in ``manifest``; ``load(name)`` reads an output
    (from a local zarr group, an object store, ...)."""
    problems = []
    try:
        for name, entry in manifest["outputs"].items():
            try:
                got = array_hash(load(name))
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
