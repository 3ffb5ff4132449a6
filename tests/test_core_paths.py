"""Structure the framework promises and that no single behaviour test would notice breaking: one execution path
for every way a stage runs, scheduling linear in the pipeline's size, and sweeps that apply ``-S vars.*`` before
anything reads the pipeline; and the CPU time of each stage in its run record."""

import json
import re
import sys
from collections import Counter

import numpy as np
import pytest
from conftest import run_cli

import msflow
import msflow.worker
from msflow import Input, Output, Result, Stage
from msflow.testing import run_stage


class Scale(Stage):
    class Params(Stage.Params):
        factor: float = 2.0

    inputs = {"x": Input.array("f")}
    outputs = {"y": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        return Result({"y": inputs["x"] * params.factor})


# ------------------------------------------------------------------------------------------------ one execution path
@pytest.fixture
def computed(monkeypatch):
    """Stage names passed through ``msflow.worker.compute``, the one function that calls a stage's ``run``."""
    seen: list[str] = []
    real = msflow.worker.compute

    def counting(cls, name, *args, **kwargs):
        seen.append(name)
        return real(cls, name, *args, **kwargs)

    monkeypatch.setattr(msflow.worker, "compute", counting)
    return seen


def test_run_sweep_and_run_stage_all_go_through_worker_compute(numproject, computed):
    from msflow.sweep import run_sweep

    result = msflow.run(numproject / "pipeline.yaml", executor="inline")
    assert sorted(computed) == sorted(result.executed) and len(computed) == 5
    computed.clear()
    sweep = run_sweep(numproject / "pipeline.yaml", [{"scaled.factor": 5}, {"scaled.factor": 6}], executor="inline")
    assert sweep.executed == 4 and len(computed) == 4 and computed.count("scaled") == 2
    computed.clear()
    out = run_stage(Scale, {"factor": 4}, {"x": np.arange(3.0)})
    assert computed == ["Scale"] and np.array_equal(out.arrays["y"], 4 * np.arange(3.0))


def test_every_executor_hands_its_jobs_to_worker_run_job():
    """Processes and Dask workers cannot be patched from here: their code must name the one entry point."""
    import ast
    import inspect

    from msflow import dask_executor, executors

    for cls in (executors.InlineExecutor, executors.ProcessExecutor, dask_executor.DaskExecutor):
        tree = ast.parse(inspect.getsource(cls.submit).lstrip().replace("\n    ", "\n"))
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        assert "run_job" in names, cls.__name__
    source = inspect.getsource(msflow.worker)
    assert source.count(".run(params, inputs)") == 1  # in compute, and nowhere else in the worker


def test_jobs_and_outcomes_cross_processes_as_the_same_json_without_copying_their_contents():
    """Job and Outcome serialise field by field (no deep copy of the manifest or key parts first): the JSON is the
    one ``dataclasses.asdict`` gave, it reads back equal, and the objects it came from are left as they were."""
    import dataclasses

    from msflow.jobs import Job, JobInput, Outcome, StageStatus

    parts = {"code": {"modules": {"a": "1" * 64}}, "params": {"factor": 2.5}, "inputs": {"x": {"hash": "2" * 64}}}
    job = Job(
        store="/s",
        store_options={"anon": True},
        project_root="/p",
        key="k" * 64,
        stage="scaled",
        uses="numstages.scaling:Scale",
        params={"factor": 2.5},
        inputs={
            "x": JobInput("array", key="u" * 64, output="y", lazy=True),
            "table": JobInput("files", files=(("t", "/d/t.csv"),), fields={"t": {"col": "x"}}),
            "gone": None,
        },
        key_parts=parts,
        checked=False,
    )
    manifest = {"outputs": {"y": {"hash": "h", "shape": [3], "dtype": "<f8"}}, "meta": {"labels": ["a", "b"]}}
    outcome = Outcome(StageStatus.RAN, manifest=manifest, seconds=0.5, worker="w", attempts=2)
    for obj, cls in ((job, Job), (outcome, Outcome)):
        text = obj.to_json()
        assert json.loads(text) == json.loads(json.dumps(dataclasses.asdict(obj)))
        assert cls.from_json(text) == obj
    assert job.key_parts is parts and outcome.manifest is manifest


# ------------------------------------------------------------------------------------------------ linear scheduling
def chain_pipeline(proj, n):
    stages = ["  s0:\n    uses: numstages.basic:Source\n    params: {n: 4}\n"]
    stages.append("  s1:\n    uses: numstages.scaling:Scale\n    inputs: {x: s0.x}\n")
    stages += [f"  s{i}:\n    uses: numstages.scaling:Scale\n    inputs: {{x: s{i - 1}.y}}\n" for i in range(2, n)]
    path = proj / f"chain{n}.yaml"
    path.write_text("version: 1\nstages:\n" + "".join(stages))
    return path


def calls_of_a_no_op_schedule(path, monkeypatch):
    """Python and C function calls made while scheduling a no-op run of ``path`` (a count, not a time)."""
    import msflow.runner

    msflow.run(path, executor="inline")
    counts: Counter[str] = Counter()
    real = msflow.runner.schedule

    def profiled(*args, **kwargs):
        def profile(frame, event, arg):
            if event in ("call", "c_call"):
                counts["calls"] += 1

        sys.setprofile(profile)
        try:
            return real(*args, **kwargs)
        finally:
            sys.setprofile(None)

    monkeypatch.setattr(msflow.runner, "schedule", profiled)
    again = msflow.run(path, executor="inline")
    assert again.executed == [] and counts["calls"] > 0
    return counts["calls"]


def test_scheduling_work_grows_linearly_with_the_number_of_stages(numproject, monkeypatch):
    small = calls_of_a_no_op_schedule(chain_pipeline(numproject, 30), monkeypatch)
    large = calls_of_a_no_op_schedule(chain_pipeline(numproject, 120), monkeypatch)
    # 4x the stages: about 4x the calls when linear, 16x when every step rescans the waiting stages
    assert large / small < 4.6, (small, large)


# ------------------------------------------------------------------------------------------------ sweeps and vars
def test_sweep_applies_vars_overrides_before_loading_the_pipeline(numproject, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "table.csv").write_text("10,20\n30,40\n")
    (numproject / "vars.yaml").write_text(
        "version: 1\nvars:\n  takes: missing-folder\n  factor: 1\nstages:\n"
        "  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {table: {path: '${takes}/table.csv'}}\n"
        "  scaled:\n    uses: numstages.scaling:Scale\n    params: {factor: '${factor}'}\n    inputs: {x: csv.x}\n"
    )
    result = run_cli(
        numproject, "sweep", "vars.yaml", "-S", f"vars.takes={elsewhere}", "-S", "vars.factor=2,3", "--format", "csv"
    )
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr and "missing-folder" not in result.stderr
    assert "[2/2] variant" in result.stderr  # the progress lines know the variants' stage count
    records = msflow.run(numproject / "vars.yaml", [f"vars.takes={elsewhere}", "vars.factor=3"])
    assert records.executed == []  # the sweep read the folder the override named
    assert np.array_equal(records.load("scaled.y"), 3 * np.array([10.0, 20, 30, 40]))


def test_a_variable_made_from_another_follows_its_override(numproject):
    """``name: ${take:stem}``: the published file is named after the file given on the command line, not after
    the default one (a capture published under the default clip's name would say it holds that clip)."""
    (numproject / "named.yaml").write_text(
        "version: 1\nvars:\n  take: data/table.csv\n  name: '${take:stem}_x'\n  file: '${take:name}'\nstages:\n"
        "  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {table: {path: '${take}'}}\n"
        "publish:\n  csv.x: out/${name}.npy\n"
    )
    (numproject / "data" / "other.csv").write_text("1,2\n")
    assert msflow.run(numproject / "named.yaml").ok and (numproject / "out" / "table_x.npy").is_file()
    msflow.run(numproject / "named.yaml", ["vars.take=data/other.csv"])
    assert np.array_equal(np.load(numproject / "out" / "other_x.npy"), [1.0, 2.0])
    assert msflow.run(numproject / "named.yaml", ["vars.name=chosen"]).ok
    assert (numproject / "out" / "chosen.npy").is_file()


# ------------------------------------------------------------------------------------------------ CPU of a stage
def test_the_run_record_and_show_give_each_stage_its_cpu_seconds_children_included(numproject):
    (numproject / "busy.yaml").write_text(
        "version: 1\nstages:\n  busy:\n    uses: numstages.basic:Busy\n    params: {cpu: 0.2, child_cpu: 0.3}\n"
    )
    run = run_cli(numproject, "run", "busy.yaml")
    assert run.returncode == 0, run.stderr
    (record,) = [json.loads(p.read_text()) for p in (numproject / ".msflow" / "runs").glob("*.json")]
    stage = record["stages"]["busy"]
    assert stage["cpu_seconds"] >= 0.5, stage  # its own 0.2 s and its child's 0.3 s
    assert "seconds" not in json.dumps(stage["key_parts"])
    summed = float(re.search(r"stages (\d+\.\d+)s CPU", run.stderr).group(1))
    assert summed == pytest.approx(stage["cpu_seconds"], abs=0.006), run.stderr
    shown = run_cli(numproject, "show", "busy", "-f", "busy.yaml")
    assert shown.returncode == 0, shown.stderr
    assert f"({stage['cpu_seconds']:.3g} s CPU)" in shown.stdout, shown.stdout
