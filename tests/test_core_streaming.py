"""Output sinks (frames-first outputs of unknown length, written chunk by chunk) and Stage.jobs."""

import json
import subprocess
import sys
import time
import tracemalloc

import numpy as np
import pytest
from conftest import cli_env, executions, run_cli

import msflow
from msflow import Output, Result, Stage, iter_blocks
from msflow.artifact import read_artifact, read_manifest
from msflow.hashing import array_hash
from msflow.stores import open_store
from msflow.stores.local import LocalStore
from msflow.testing import run_stage


def stored_files(path):
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


class Frames(Stage):
    class Params(Stage.Params):
        rows: list[int] = [3, 0, 5]
        width: int = 4

    outputs = {"x": Output.array("f", shape=("frames", None)), "n": Output.array("i", shape=("frames",))}

    def run(self, params, inputs):
        x = self.sink("x", dtype=np.float64, row_shape=(params.width,))
        n = self.sink("n", dtype=np.int64)
        start = 0
        for m in params.rows:
            x.append(np.arange(start * params.width, (start + m) * params.width, dtype=float).reshape(m, params.width))
            n.append(np.arange(start, start + m))
            start += m
        return Result({"x": x, "n": n}, meta={"rows": len(x)})


def whole(rows, width):
    total = sum(rows)
    return np.arange(total * width, dtype=float).reshape(total, width), np.arange(total)


@pytest.mark.parametrize("rows", [[], [0], [1], [3, 0, 5], [7, 7, 7, 7, 1]])
def test_sink_hash_and_stored_bytes_equal_a_whole_array(tmp_path, monkeypatch, rows):
    monkeypatch.setattr("msflow.chunks.CHUNK_BYTES", 4 * 8 * 7)  # 7 rows a chunk: ragged and exact edges
    store = LocalStore(tmp_path / "store")
    with store.writer("k1") as writer:
        stage = Frames("frames", chunk_target=writer)
        from msflow.stage import validate_result

        result = stage.run(Frames.Params(rows=rows), {})
        sunk = writer.commit(validate_result("frames", Frames, result), {"meta": result.meta})
    x, n = whole(rows, 4)
    direct = store.write("k2", {"x": x, "n": n}, {"meta": {"rows": len(x)}})
    assert sunk == direct
    assert sunk["outputs"]["x"]["hash"] == array_hash(x) and sunk["outputs"]["n"]["hash"] == array_hash(n)
    assert stored_files(store.artifact_path("k1")) == stored_files(store.artifact_path("k2"))
    view = store.open("k1")
    assert np.array_equal(view["x"], x) and np.array_equal(view["n"], n)
    assert store.verify("k1") == [] and list((tmp_path / "store" / "tmp").iterdir()) == []


def test_sink_checks_blocks_and_schema():
    stage = Frames("f")
    sink = stage.sink("x", dtype="float32", row_shape=(4,))
    with pytest.raises(ValueError, match=r"block of shape \(2, 3\), expected \(m, 4\)"):
        sink.append(np.zeros((2, 3)))
    with pytest.raises(TypeError, match="cannot store complex128"):
        sink.append(np.zeros((2, 4), complex))
    sink.append(np.ones((2, 4), np.float64))  # same kind: cast to the sink's dtype
    assert len(sink) == 2 and sink.shape == (2, 4) and sink.to_array().dtype == np.float32
    with pytest.raises(ValueError, match="already has a sink"):
        stage.sink("x", dtype="float32", row_shape=(4,))
    with pytest.raises(ValueError, match="no declared output 'y'"):
        stage.sink("y", dtype="float32")
    with pytest.raises(TypeError, match="dtype int32 is not of kind float"):
        Frames("g").sink("x", dtype="int32", row_shape=(4,))
    with pytest.raises(ValueError, match="2 dimensions"):
        Frames("h").sink("n", dtype="int32", row_shape=(4,))


def test_run_stage_supports_sinks_and_rejects_what_the_runner_rejects():
    out = run_stage(Frames, {"rows": [2, 3]})
    x, n = whole([2, 3], 4)
    assert np.array_equal(out.arrays["x"], x) and np.array_equal(out.arrays["n"], n) and out.meta == {"rows": 5}

    class BadMetrics(Stage):
        outputs = {"y": Output.array("f", ndim=1)}

        def run(self, params, inputs):
            return Result({"y": np.zeros(2)}, metrics={"curve": [1.0, 2.0]})

    with pytest.raises(ValueError, match="metrics must be scalar numbers"):
        run_stage(BadMetrics)

    class Mismatch(Stage):
        outputs = {"a": Output.array("f", shape=("frames",)), "b": Output.array("f", shape=("frames",))}

        def run(self, params, inputs):
            a = self.sink("a", dtype="f8")
            a.append(np.zeros(3))
            return Result({"a": a, "b": np.zeros(4)})

    with pytest.raises(ValueError, match="dimension 'frames' is 4 here but 3"):
        run_stage(Mismatch)


def test_iter_blocks_reads_lazy_inputs_block_by_block(tmp_path):
    x = np.arange(50.0).reshape(25, 2)
    assert np.array_equal(np.concatenate(list(iter_blocks(x, 4))), x)
    store = LocalStore(tmp_path)
    store.write("k", {"x": x}, {})
    lazy = store.open("k").lazy("x")
    assert [b.shape[0] for b in iter_blocks(lazy, 10)] == [10, 10, 5]
    assert np.array_equal(np.concatenate(list(iter_blocks(lazy))), x)
    with pytest.raises(ValueError, match="first"):
        list(iter_blocks(np.float64(1.0)))


def test_sinks_on_an_object_store_match_a_local_one(tmp_path):
    remote = open_store(f"memory://sinks-{tmp_path.name}", {})
    local = LocalStore(tmp_path / "local")
    manifests = []
    for store in (remote, local):
        with store.writer("k") as writer:
            stage = Frames("f", chunk_target=writer)
            from msflow.stage import validate_result

            result = stage.run(Frames.Params(rows=[5, 70_000, 3], width=8), {})
            manifests.append(writer.commit(validate_result("f", Frames, result), {"meta": result.meta}))
    assert manifests[0] == manifests[1]
    x, n = whole([5, 70_000, 3], 8)
    view = remote.open("k")
    assert np.array_equal(view["x"], x) and np.array_equal(view["x"][69_990:70_008], x[69_990:70_008])
    assert np.array_equal(np.concatenate(list(iter_blocks(view.lazy("x")))), x)
    assert remote.verify("k") == []


def test_streamed_and_whole_outputs_give_identical_hashes_in_a_run(numproject):
    out = msflow.run(numproject / "stream.yaml")
    streamed, whole_ = (out.states[n].manifest["outputs"] for n in ("streamed", "whole"))
    assert streamed == whole_
    frames = out.load("streamed.frames")
    assert frames.shape == (270_000, 16) and frames.dtype == np.float32
    assert np.isclose(out.load("total.total"), frames.astype(np.float64).sum())
    assert run_cli(numproject, "verify", "stream.yaml").returncode == 0


def peak_memory_of_a_streamed_run(proj, name, blocks, rows, width):
    (proj / f"{name}.yaml").write_text(
        f"version: 1\nstages:\n  {name}:\n    uses: numstages.basic:Stream\n"
        f"    params: {{blocks: {blocks}, rows: {rows}, width: {width}}}\n"
    )
    tracemalloc.start()
    try:
        out = msflow.run(proj / f"{name}.yaml")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert out.executed == [name]
    assert out.states[name].manifest["outputs"]["frames"]["shape"] == [rows * blocks, width]
    return peak


def test_a_sinked_output_is_never_held_in_memory_whole(numproject):
    # 24 MB and 96 MB of float32 frames: the sink holds at most one 4 MB chunk, so the peak does not grow
    rows, width = 62_500, 16
    small = peak_memory_of_a_streamed_run(numproject, "small", 6, rows, width)
    big = peak_memory_of_a_streamed_run(numproject, "big", 24, rows, width)
    size = 24 * rows * width * 4
    assert big < size / 4, f"peak {big / 1e6:.1f} MB for a {size / 1e6:.0f} MB output"
    assert big - small < 0.1 * (size - size / 4), f"peak {small / 1e6:.1f} MB at 24 MB, {big / 1e6:.1f} MB at 96 MB"


def test_a_run_killed_mid_sink_leaves_nothing_visible_and_the_next_run_recovers(numproject, tmp_path):
    hold = tmp_path / "hold"
    hold.mkdir()
    proc = subprocess.Popen(
        [sys.executable, "-m", "msflow.cli", "run", "stream.yaml", "--until", "streamed", "-q"],
        cwd=numproject,
        env=cli_env({"NUMSTAGES_HOLD": str(hold)}),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60
        while not (hold / "ready").exists():  # the stage is now waiting, with chunks already written
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.01)
        tmp = numproject / ".msflow" / "tmp"
        written = [p for p in tmp.rglob("*") if p.is_file() and "/frames/c/" in p.as_posix()]
        assert written, "no chunk was written before the end of the stage"
    finally:
        proc.kill()
        proc.wait()
    artifacts = numproject / ".msflow" / "artifacts"
    assert not artifacts.exists() or not any(artifacts.glob("*/*"))
    result = run_cli(numproject, "run", "stream.yaml", "-q")
    assert result.returncode == 0, result.stderr
    assert list((numproject / ".msflow" / "tmp").iterdir()) == []
    assert run_cli(numproject, "verify", "stream.yaml").returncode == 0
    record = json.loads(sorted((numproject / ".msflow" / "runs").glob("*.json"))[-1].read_text())
    assert record["stages"]["streamed"]["outputs"] == record["stages"]["whole"]["outputs"]
    view = read_artifact(artifacts / record["stages"]["streamed"]["key"][:2] / record["stages"]["streamed"]["key"])
    assert read_manifest(artifacts / record["stages"]["whole"]["key"][:2] / record["stages"]["whole"]["key"])
    assert view["frames"].shape == (270_000, 16)


def test_jobs_reaches_the_stage_and_stays_out_of_the_key(numproject, tmp_path):
    logs = []
    for jobs in (1, 2):
        log = tmp_path / f"log{jobs}"
        result = run_cli(
            numproject, "run", "stream.yaml", "--until", "streamed", "-j", jobs, "--force", "streamed", "-q",
            env={"NUMSTAGES_LOG": str(log)},
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        logs.append(log.read_text())
    assert "streamed jobs=1" in logs[0] and "streamed jobs=2" in logs[1]
    records = sorted((numproject / ".msflow" / "runs").glob("*.json"))
    keys = [json.loads(p.read_text())["stages"]["streamed"]["key"] for p in records]
    assert len(keys) == 2 and keys[0] == keys[1]
    assert executions(tmp_path / "log1") == ["streamed"]


@pytest.mark.parametrize("where", ["local", "object store", "object store, no packs"])
def test_a_sink_opened_but_not_returned_leaves_no_files(tmp_path, where, monkeypatch):
    from msflow.stores.packs import PACK_NAME, Pack

    if where.endswith("no packs"):
        monkeypatch.setenv("MSFLOW_STORE_PACK_MB", "0")  # the sink's chunks are uploaded as they fill

    class Undecided(Stage):
        outputs = {"a": Output.array("f", ndim=1, optional=True), "b": Output.array("f", ndim=1)}

        def run(self, params, inputs):
            a = self.sink("a", dtype="f8")
            a.append(np.zeros(600_000))  # more than a chunk: some of it was written
            return Result({"b": np.ones(2)})

    store = LocalStore(tmp_path) if where == "local" else open_store(f"memory://undecided-{tmp_path.name}", {})
    with store.writer("k") as writer:
        stage = Undecided("u", chunk_target=writer)
        from msflow.stage import validate_result

        writer.commit(validate_result("u", Undecided, stage.run(None, {})), {})
    if where == "local":
        assert sorted(p.name for p in store.artifact_path("k").iterdir()) == ["b", "zarr.json"]
    else:
        folder = writer.folder + "/"
        names = {i.path[len(folder) :] for i in store.objects.list(folder)}
        if names == {PACK_NAME}:
            names = {rel for rel, _ in Pack(store.objects.get(folder + PACK_NAME), folder).members()}
        assert {name.split("/")[0] for name in names} == {"b", "zarr.json"}
    assert np.array_equal(store.open("k")["b"], np.ones(2))
