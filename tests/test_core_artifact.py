"""The artifact format: zarr v3 written by msflow, read by zarr, hashed by content."""

import json

import numpy as np
import pytest
import zarr

from msflow.artifact import read_artifact, read_manifest, verify_artifact, write_artifact
from msflow.hashing import array_hash
from msflow.stage import to_strict_json

ARRAYS = {
    "scalar": np.array(3.25),
    "empty": np.zeros((0, 68, 2), np.float32),
    "flags": np.array([True, False, True]),
    "bytes": np.frombuffer(b"glTF\x02\x00", np.uint8),
    "ints": np.arange(-5, 5, dtype=np.int64).reshape(2, 5),
    "big_endian": np.arange(6, dtype=">f8"),
    "multi_chunk": np.random.default_rng(0).standard_normal((700, 68, 2)).astype(np.float32),
    "crops": np.random.default_rng(1).integers(0, 255, (300, 128, 128), dtype=np.uint8),
    "complex": np.array([1 + 2j, 3 - 4j]),
}


def test_zarr_reads_what_msflow_writes(tmp_path, monkeypatch):
    monkeypatch.setattr("msflow.chunks.CHUNK_BYTES", 100_000)  # force several chunks, with a ragged edge
    path = tmp_path / "a"
    manifest = write_artifact(path, ARRAYS, {"meta": {"labels": ["n", "h"]}, "metrics": {"m": 1.5}})
    group = zarr.open_group(str(path), mode="r")
    for name, arr in ARRAYS.items():
        got = group[name][...]
        assert got.shape == arr.shape and np.array_equal(got, arr), name
        assert manifest["outputs"][name]["hash"] == array_hash(arr)
    assert group["multi_chunk"].chunks[0] < 700 and 700 % group["multi_chunk"].chunks[0] != 0
    assert group.attrs["msflow"]["meta"] == {"labels": ["n", "h"]}
    view = read_artifact(path)
    assert view.metrics == {"m": 1.5} and view["scalar"].shape == ()
    assert verify_artifact(path) == []
    assert read_manifest(path)["content_hash"] == manifest["content_hash"]


def test_msflow_reads_runs_of_rows_across_chunks_as_zarr_does(tmp_path):
    """Reads without zarr (msflow.stored): whole arrays and runs of rows that start and end inside chunks equal
    zarr's reading of the same folder, in native byte order and writable; other selections go through zarr."""
    rng = np.random.default_rng(3)
    arrays = {"pairs": rng.standard_normal((300_000, 2)), "scalar": np.array(7, dtype=">i4"), "empty": np.zeros((0, 3))}
    write_artifact(tmp_path / "a", arrays, {"meta": {}, "metrics": {}})
    view = read_artifact(tmp_path / "a")
    group = zarr.open_group(str(tmp_path / "a"), mode="r")
    stored = view.lazy("pairs")
    assert stored.chunks == group["pairs"].chunks and stored.chunks[0] < 300_000  # two chunks
    edge = stored.chunks[0]
    for rows in (slice(edge - 5, edge + 7), slice(0, 3), slice(edge, None), slice(10, 10), slice(None)):
        got = stored[rows]
        assert np.array_equal(got, group["pairs"][rows]) and got.flags.writeable, rows
    assert np.array_equal(stored[[1, edge + 1]], arrays["pairs"][[1, edge + 1]])  # fancy indexing: zarr's
    assert view["scalar"] == 7 and view["scalar"].dtype == np.dtype("i4") and view["empty"].shape == (0, 3)


def test_reading_a_stored_array_holds_it_about_once(tmp_path):
    """A whole output read from a folder is decoded chunk by chunk into the result, so memory peaks near the
    array's own size (gathering the decoded chunks, concatenating and copying held it three times)."""
    import tracemalloc

    big = np.random.default_rng(0).standard_normal(6_000_000)  # 48 MB: 12 chunks of 4 MB
    write_artifact(tmp_path / "a", {"big": big}, {"meta": {}, "metrics": {}})
    view = read_artifact(tmp_path / "a")
    tracemalloc.start()
    try:
        got = view["big"]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert np.array_equal(got, big)
    assert peak < 1.5 * big.nbytes, f"peak {peak / big.nbytes:.2f}x the array"


def test_content_hash_ignores_storage_but_not_values(tmp_path):
    a = write_artifact(tmp_path / "a", {"x": np.arange(4.0)}, {"meta": {}})
    b = write_artifact(tmp_path / "b", {"x": np.arange(4.0).astype(">f8")}, {"meta": {}})
    c = write_artifact(tmp_path / "c", {"x": np.arange(4.0) + 1e-12}, {"meta": {}})
    d = write_artifact(tmp_path / "d", {"x": np.arange(4.0)}, {"meta": {"k": 1}})
    assert a["content_hash"] == b["content_hash"]
    assert len({a["content_hash"], c["content_hash"], d["content_hash"]}) == 3
    assert array_hash(np.arange(4.0)) != array_hash(np.arange(4.0).reshape(2, 2))


def test_write_refuses_existing_path(tmp_path):
    write_artifact(tmp_path / "a", {"x": np.zeros(2)}, {})
    with pytest.raises(FileExistsError):
        write_artifact(tmp_path / "a", {"x": np.zeros(2)}, {})


def test_strict_json_converts_numpy_and_rejects_nan():
    assert to_strict_json({"a": np.float32(1.5), "b": np.arange(3), "c": (1, np.int64(2))}, "m") == {
        "a": 1.5,
        "b": [0, 1, 2],
        "c": [1, 2],
    }
    for bad in (float("nan"), float("inf"), np.float64("nan"), {"x": [1.0, float("-inf")]}):
        with pytest.raises(ValueError, match="not allowed in strict JSON"):
            to_strict_json(bad, "meta")
    with pytest.raises(ValueError, match="is not JSON"):
        to_strict_json({"f": object()}, "meta")
    json.dumps(to_strict_json({"z": np.bool_(True)}, "m"), allow_nan=False)
