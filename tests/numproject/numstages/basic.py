"""Numeric test stages. NUMSTAGES_LOG (env) names a file that gets one line per execution: a side channel for
counting executions that is not part of any cache key. NUMSTAGES_HOLD (env) names a folder: Slow (before
computing) and Stream (in the middle of its output) write <folder>/ready and wait for <folder>/release, so tests
can kill or race a run at a known point without sleeping."""

import os
import time
from functools import partial

import numpy as np

from msflow import Input, Output, Result, Stage, UserError, iter_blocks


def log_execution(name):
    path = os.environ.get("NUMSTAGES_LOG")
    if path:
        with open(path, "a") as fh:
            fh.write(f"{name} {os.getpid()}\n")


class Source(Stage):
    class Params(Stage.Params):
        n: int = 5
        offset: float = 0.0

    outputs = {"x": Output.array("f", shape=("n",))}

    def run(self, params, inputs):
        log_execution(self.name)
        return Result(
            {"x": np.arange(params.n, dtype=float) + params.offset}, meta={"n": params.n}, metrics={"n": params.n}
        )


class Sign(Stage):
    """Output depends only on the sign of the input: reruns often produce identical content (early cutoff)."""

    inputs = {"x": Input.array("f")}
    outputs = {"s": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        log_execution(self.name)
        return Result({"s": np.sign(inputs["x"])})


class Sum(Stage):
    inputs = {"a": Input.artifact(), "b": Input.array("f", optional=True)}
    outputs = {"total": Output.array("f", shape=())}

    def run(self, params, inputs):
        log_execution(self.name)
        view = inputs["a"]
        total = sum(float(view[n].sum()) for n in view.names)
        if inputs["b"] is not None:
            total += float(inputs["b"].sum())
        return Result({"total": np.array(total)}, metrics={"total": total})


class LoadCsv(Stage):
    inputs = {"table": Input.files()}
    outputs = {"x": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        log_execution(self.name)
        (path,) = inputs["table"].values()
        try:
            return Result({"x": np.loadtxt(path, delimiter=",", ndmin=2).reshape(-1)})
        except ValueError as exc:
            raise UserError(f"not a numeric CSV: {exc}", file=str(path), field="inputs.table") from None


class Slow(Stage):
    """Returns a large array; with NUMSTAGES_HOLD it first waits for a release file (a kill point)."""

    class Params(Stage.Params):
        size: int = 2_000_000
        seed: int = 0

    inputs = {"x": Input.array("f", optional=True)}
    outputs = {"big": Output.array("f", ndim=1), "small": Output.array("i", ndim=1)}

    def run(self, params, inputs):
        log_execution(self.name)
        hold_if_asked(self.name)
        rng = np.random.default_rng(params.seed)
        return Result({"big": rng.standard_normal(params.size), "small": np.arange(10)})


class Broken(Stage):
    """Returns the wrong thing, or raises: for failure handling tests."""

    class Params(Stage.Params):
        mode: str = "schema"

    outputs = {"y": Output.array("f", shape=(3,))}

    def run(self, params, inputs):
        if params.mode == "schema":
            return Result({"y": np.zeros(4)})
        if params.mode == "nan_meta":
            return Result({"y": np.zeros(3)}, meta={"bad": float("nan")})
        if params.mode == "user":
            raise UserError("the data is unusable", field="inputs.x")
        if params.mode == "fine":
            return Result({"y": np.ones(3)}, metrics={"score": 1.0})
        raise RuntimeError("boom")


class NotAStage:
    pass


class Reference(Stage):
    """Reads a data file its code depends on (a resource), not an input."""

    resources = {"ref": __import__("pathlib").Path(__file__).resolve().parents[1] / "data" / "reference.txt"}
    outputs = {"v": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        log_execution(self.name)
        return Result({"v": np.loadtxt(self.resources["ref"], ndmin=1)})


class LoadFolder(Stage):
    """Sums the numbers in every file of a folder input."""

    inputs = {"folder": Input.files()}
    outputs = {"total": Output.array("f", shape=())}

    def run(self, params, inputs):
        log_execution(self.name)
        (folder,) = inputs["folder"].values()
        files = sorted(p for p in folder.iterdir() if p.is_file())
        return Result({"total": np.array(sum(np.loadtxt(p, ndmin=1).sum() for p in files))})


class DieOnce(Stage):
    """Kills its own process the first time it runs (a worker dying mid-stage), succeeds afterwards.

    NUMSTAGES_MARKER names the file that records the first attempt."""

    inputs = {"x": Input.array("f")}
    outputs = {"y": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        import signal

        marker = os.environ["NUMSTAGES_MARKER"]
        if not os.path.exists(marker):
            with open(marker, "w") as fh:
                fh.write(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)
        log_execution(self.name)
        return Result({"y": inputs["x"] + 1})


class Burn(Stage):
    """CPU-bound work of a fixed amount (for executor speed-up benchmarks)."""

    class Params(Stage.Params):
        rounds: int = 200
        seed: int = 0

    outputs = {"v": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        log_execution(self.name)
        rng = np.random.default_rng(params.seed)
        m = rng.standard_normal((200, 200)) / 20
        v = rng.standard_normal(200)
        for _ in range(params.rounds):
            v = np.tanh(m @ v + np.sin(v))
        return Result({"v": v})


class Busy(Stage):
    """Uses at least ``cpu`` CPU seconds itself and ``child_cpu`` in a child process it waits for (a known amount
    of CPU for the run record's cpu_seconds; a loop on CPU time, not a sleep)."""

    class Params(Stage.Params):
        cpu: float = 0.0
        child_cpu: float = 0.0

    outputs = {"v": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        import subprocess
        import sys

        spin = "import time\nstart = time.process_time()\nwhile time.process_time() - start < {}: pass\n"
        exec(spin.format(params.cpu), {})
        if params.child_cpu:
            subprocess.run([sys.executable, "-c", spin.format(params.child_cpu)], check=True)
        return Result({"v": np.zeros(2)})


class Cautious(Stage):
    """A usable result with warnings: one attached to the Result, one raised with warnings.warn."""

    class Params(Stage.Params):
        limit: int = 3

    outputs = {"x": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        import warnings

        log_execution(self.name)
        notes = [f"stopped at the iteration limit ({params.limit}) before converging"] if params.limit < 10 else []
        warnings.warn("input looks constant", UserWarning)
        warnings.warn("numeric detail", DeprecationWarning)  # not the user's business: not collected
        return Result({"x": np.zeros(params.limit)}, warnings=notes)


class Takes(Stage):
    """Reports the labels and fields of its files (takes as data)."""

    inputs = {"takes": Input.files()}
    outputs = {"sizes": Output.array("i", ndim=1)}

    def run(self, params, inputs):
        log_execution(self.name)
        takes = inputs["takes"]
        sizes = np.array([path.stat().st_size for path in takes.values()], dtype=np.int64)
        return Result({"sizes": sizes}, meta={"labels": list(takes), "fields": takes.fields})


def hold_if_asked(name):
    """A deterministic kill point: with NUMSTAGES_HOLD=<folder>, write <folder>/ready and wait until
    <folder>/release exists (tests kill the process while it waits)."""
    folder = os.environ.get("NUMSTAGES_HOLD")
    if not folder:
        return
    partial = os.path.join(folder, f"ready.{os.getpid()}")
    with open(partial, "w") as fh:
        fh.write(f"{name} {os.getpid()}\n")
    os.replace(partial, os.path.join(folder, "ready"))  # the test reads the line as soon as the file exists
    while not os.path.exists(os.path.join(folder, "release")):
        time.sleep(0.01)


def stream_block(seed, index, rows, width):
    """Block ``index`` of the Stream stage's output: deterministic, different per block."""
    return np.random.default_rng([seed, index]).standard_normal((rows, width), dtype=np.float32)


class Stream(Stage):
    """A long frames-first output written block by block through an output sink (``whole``: returned whole)."""

    class Params(Stage.Params):
        blocks: int = 8
        rows: int = 1000
        width: int = 16
        seed: int = 0
        whole: bool = False

    outputs = {"frames": Output.array("f", shape=("frames", None)), "norms": Output.array("f", shape=("frames",))}

    def run(self, params, inputs):
        log_execution(f"{self.name} jobs={self.jobs}")
        blocks = (stream_block(params.seed, i, params.rows, params.width) for i in range(params.blocks))
        if params.whole:
            frames = np.concatenate(list(blocks)) if params.blocks else np.zeros((0, params.width), np.float32)
            return Result({"frames": frames, "norms": np.linalg.norm(frames, axis=1)})
        frames = self.sink("frames", dtype=np.float32, row_shape=(params.width,))
        norms = self.sink("norms", dtype=np.float32)
        for index, block in enumerate(blocks):
            frames.append(block)
            norms.append(np.linalg.norm(block, axis=1))
            if index == params.blocks // 2:
                hold_if_asked(self.name)
        return Result({"frames": frames, "norms": norms})


class BlockSum(Stage):
    """Sums a lazy input block by block (iter_blocks)."""

    inputs = {"x": Input.array("f", lazy=True)}
    outputs = {"total": Output.array("f", shape=())}

    def run(self, params, inputs):
        from msflow import iter_blocks

        log_execution(self.name)
        total = sum(float(block.astype(np.float64).sum()) for block in iter_blocks(inputs["x"]))
        return Result({"total": np.array(total)})


def tiny_png(view, inputs):
    """A report figure without matplotlib: a 1x1 grey PNG."""
    import base64

    return base64.b64decode(
        "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAAAAAA6fptVAAAACklEQVR4nGNoAAAAggCBd81ytgAAAABJRU5ErkJggg=="
    )


class Pictured(Stage):
    """A stage with a report figure."""

    class Params(Stage.Params):
        size: int = 2

    outputs = {"x": Output.array("f", ndim=1)}
    figures = {"dot": tiny_png}

    def run(self, params, inputs):
        return Result({"x": np.zeros(params.size)})


class Tagged(Stage):
    """A param whose type is a union (pydantic tags its errors with the member types)."""

    class Params(Stage.Params):
        k: int | list[int] = 1

    outputs = {"x": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        return Result({"x": np.zeros(1)})


class Gaps(Stage):
    """Float outputs without a finite value (all NaN; NaN and Inf), returned whole and through sinks, beside
    outputs with some (one finite value, only in the last block) and an empty one: for the non-finite warning."""

    class Params(Stage.Params):
        blocks: int = 3
        rows: int = 4

    outputs = {
        "nan": Output.array("f", ndim=1),
        "nan_inf": Output.array("f", ndim=1),
        "one_finite": Output.array("f", ndim=1),
        "empty": Output.array("f", ndim=1),
        "streamed_nan": Output.array("f", shape=("frames", 2)),
        "streamed_late": Output.array("f", shape=("frames",)),
        "count": Output.array("i", ndim=1),
    }

    def run(self, params, inputs):
        streamed_nan = self.sink("streamed_nan", dtype=np.float32, row_shape=(2,))
        streamed_late = self.sink("streamed_late", dtype=np.float64)
        for index in range(params.blocks):
            streamed_nan.append(np.full((params.rows, 2), np.nan, np.float32))
            late = np.full(params.rows, np.nan)
            late[-1] = 1.0 if index == params.blocks - 1 else np.nan
            streamed_late.append(late)
        arrays = {
            "nan": np.full(params.rows, np.nan),
            "nan_inf": np.array([np.nan, np.inf, -np.inf]),
            "one_finite": np.array([np.nan, np.inf, 2.0]),
            "empty": np.zeros(0),
            "streamed_nan": streamed_nan,
            "streamed_late": streamed_late,
            "count": np.arange(params.rows),
        }
        return Result(arrays)


# ---- a stage built from parts (Stage.part): each take's values are computed and stored on their own, so a run
# with one more take computes only that take's part. Each part computed logs ``part <file name>`` to
# NUMSTAGES_LOG, and holds there with NUMSTAGES_HOLD (hold_if_asked).


def take_values(path, scale, offset, sink):
    """One take's part: the numbers in its file, scaled and offset."""
    log_execution(f"part {path.name}")
    hold_if_asked(f"part {path.name}")
    values = sink("values", dtype=np.float64)
    values.append(np.loadtxt(path, ndmin=1) * scale + offset)
    return Result({"values": values}, meta={"rows": len(values)})


class PerTake(Stage):
    """Every take's values end to end, and the index of the take each row came from."""

    class Params(Stage.Params):
        scale: float = 1.0
        comment: str = ""  # read by no part (Stage.part's unread_params)

    inputs = {"takes": Input.files(), "offset": Input.files(optional=True)}
    outputs = {"values": Output.array("f", shape=("rows",)), "take": Output.array("i", shape=("rows",))}

    def run(self, params, inputs):
        log_execution(self.name)
        offset = float(np.loadtxt(next(iter(inputs["offset"].values())))) if inputs["offset"] else 0.0
        values = self.sink("values", dtype=np.float64)
        takes = []
        for index, (label, path) in enumerate(inputs["takes"].items()):
            make = partial(take_values, path, params.scale, offset)
            part = self.part(label, make, labelled=("takes",), whole=("offset",), unread_params=("comment",))
            for block in iter_blocks(part.arrays["values"]):
                values.append(block)
            takes.append(np.full(part.meta["rows"], index, dtype=np.int64))
        return Result({"values": values, "take": np.concatenate(takes)})
