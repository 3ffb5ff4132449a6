"""What the command line says: --version, output cut off by a closed pipe, the runs listing, the wording of its
messages and the hints naming the pipeline file the user probably meant."""

import json
import os
import subprocess
import sys
from importlib import metadata

import pytest
from conftest import cli_env, run_cli
from pydantic import field_validator

from msflow import Stage, UserError
from msflow.plan import canonical_params
from msflow.version import __version__


def test_version_is_the_installed_distributions(numproject):
    result = run_cli(numproject, "--version")
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"msflow {metadata.version('msflow')}\n"


def test_version_of_a_tree_never_installed_is_the_modules(monkeypatch):
    from msflow.version import package_version

    def not_installed(name):
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metadata, "version", not_installed)
    assert package_version() == __version__


def into_a_closed_pipe(cwd, *args, env=None):
    """Run ``msflow ARGS`` with stdout a pipe nobody reads any more (``msflow ... | head`` once head has quit):
    the read end is closed before the process starts, so its very first write fails, every time."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        command = [sys.executable, "-m", "msflow.cli", *map(str, args)]
        return subprocess.run(command, cwd=cwd, env=cli_env(env), stdout=write_end, stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(write_end)


@pytest.mark.parametrize("args", [["show", "src"], ["runs"], ["status"], ["dag"]])
def test_output_into_a_closed_pipe_stops_quietly_with_141(numproject, args):
    """141 (128 + SIGPIPE) is what a shell reports for `yes`, `cat` or `git log` piped into head; nothing on
    stderr: no traceback, no "Exception ignored". `status` after a run is the no-op fast path's answer."""
    assert run_cli(numproject, "run", "-q").returncode == 0
    result = into_a_closed_pipe(numproject, *args)
    assert (result.returncode, result.stderr.decode()) == (141, "")


def test_the_fast_paths_status_into_a_closed_pipe_is_not_answered_again(numproject):
    """The no-op status is printed once its state holds: a closed stdout is no doubt handing over to the full
    path (which would compute every key only to fail on the same pipe)."""
    assert run_cli(numproject, "run", "-q").returncode == 0
    result = into_a_closed_pipe(numproject, "status", env={"MSFLOW_FASTPATH_DEBUG": "1"})
    assert (result.returncode, result.stderr.decode()) == (141, "")  # the debug switch says why it hands over


def test_runs_names_each_runs_pipeline_and_the_file_argument_filters(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert run_cli(numproject, "run", "-q", "warnings.yaml").returncode == 0
    records = sorted((numproject / ".msflow" / "runs").glob("*.json"))
    default_run, warnings_run = (path.stem for path in records)
    everything = run_cli(numproject, "runs").stdout.splitlines()
    assert [line.split()[:1] + line.split()[3:4] for line in everything] == [
        [default_run, "pipeline.yaml"],
        [warnings_run, "warnings.yaml"],
    ]
    only = run_cli(numproject, "runs", "warnings.yaml").stdout
    assert warnings_run in only and default_run not in only and "warnings.yaml" not in only  # no column to repeat
    assert run_cli(numproject, "runs", "crash.yaml").stdout == "no runs of crash.yaml yet\n"


def test_runs_lists_a_record_without_a_pipeline_but_filters_it_out(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    (path,) = (numproject / ".msflow" / "runs").glob("*.json")
    record = json.loads(path.read_text())
    del record["pipeline"]
    path.write_text(json.dumps(record))
    listed = run_cli(numproject, "runs")
    assert listed.returncode == 0 and f"{path.stem}  ok" in listed.stdout and "s  ?  5 ran" in listed.stdout
    assert run_cli(numproject, "runs", "pipeline.yaml").stdout == "no runs of pipeline.yaml yet\n"


@pytest.mark.parametrize(
    "args, message",
    [
        (["run", "--until", "nosuch"], "field '--until': unknown stage 'nosuch'; stages: ['csv', 'scaled', "),
        (["run", "--force", "nosuch"], "field '--force': unknown stage(s) ['nosuch']"),
        (["show", "nosuch"], "field 'STAGE': unknown stage 'nosuch'; stages: ['csv', 'scaled', 'sign', "),
        (["why", "srcc"], "unknown stage 'srcc' (did you mean 'src'?); stages: ['csv', "),
    ],
)
def test_an_unknown_stage_is_named_once_with_the_stages_there_are(numproject, args, message):
    result = run_cli(numproject, *args)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert result.stderr.count(args[1]) == 1  # the option or the name, said once


class Counted(Stage):
    class Params(Stage.Params):
        k: int = 1

        @field_validator("k")
        @classmethod
        def _positive(cls, k):
            if k < 1:
                raise ValueError(f"k must be at least 1, got {k}")
            return k


def test_a_params_validators_own_message_is_not_followed_by_another_got():
    with pytest.raises(UserError) as refused:
        canonical_params(Counted, {"k": -3}, file="p.yaml", stage="count")
    assert str(refused.value) == "p.yaml: stage 'count': field 'params.k': k must be at least 1, got -3"
    with pytest.raises(UserError) as mistyped:  # pydantic's own words name no value: the input is added
        canonical_params(Counted, {"k": "many"}, file="p.yaml", stage="count")
    assert str(mistyped.value).endswith(
        "Input should be a valid integer, unable to parse string as an integer (got 'many')"
    )


def test_a_variable_of_another_pipeline_file_names_that_file(numproject):
    (numproject / "pipelines").mkdir()
    capture = "version: 1\nvars: {take: a.mp4}\nstages:\n  src:\n    uses: numstages.basic:Source\n"
    (numproject / "pipelines" / "capture.yaml").write_text(capture)
    (numproject / "pipelines" / "notes.yaml").write_text("take: not a pipeline\n")
    result = run_cli(numproject, "run", "-S", "vars.take=x.mp4")
    assert result.returncode == 2, result.stderr
    assert (
        "unknown variable 'take'; the pipeline's vars: ['n']; pipelines/capture.yaml has 'take' "
        "(the pipeline file you meant?)" in result.stderr
    ), result.stderr
    assert "notes.yaml" not in result.stderr
    nowhere = run_cli(numproject, "run", "-S", "vars.clip=x.mp4")
    assert nowhere.returncode == 2 and nowhere.stderr.rstrip().endswith("the pipeline's vars: ['n']")


def test_a_missing_pipeline_file_names_the_projects_file_of_that_name(numproject):
    (numproject / "pyproject.toml").write_text("")  # marks the project root, as in a real project
    (numproject / "eval").mkdir()
    (numproject / "eval" / "face.yaml").write_text((numproject / "pipeline.yaml").read_text())
    result = run_cli(numproject, "run", "face.yaml")
    assert result.returncode == 2
    assert "face.yaml: pipeline file not found; did you mean eval/face.yaml? (give it as the FILE argument)" in (
        result.stderr
    )
    (numproject / "out").mkdir()
    below = run_cli(numproject / "out", "status", "face.yaml")
    assert "did you mean ../eval/face.yaml?" in below.stderr, below.stderr


def test_msflow_alone_shows_the_help_and_no_empty_error(numproject):
    result = run_cli(numproject)
    assert "Usage: msflow" in result.stdout and "run " in result.stdout
    assert result.returncode == 2 and "error" not in result.stderr, result.stderr


BAD_SHAPE = """
import numpy as np
from msflow import Output, Result, Stage


class Flat(Stage):
    outputs = {"y": Output.array("f", shape=("n",))}

    def run(self, params, inputs):
        return Result({"y": np.zeros((1, 4))})
"""


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_a_result_that_breaks_its_schema_is_said_once_without_msflows_traceback(numproject, jobs):
    """Before: "stage 'flat' failed: StageFailed: stage 'flat' failed: stage 'flat', output 'y': ..." and two
    chained tracebacks from msflow's worker, none of them the stage's code."""
    (numproject / "numstages" / "flat.py").write_text(BAD_SHAPE)
    (numproject / "flat.yaml").write_text("version: 1\nstages:\n  flat:\n    uses: numstages.flat:Flat\n")
    result = run_cli(numproject, "run", "flat.yaml", "-j", jobs)
    assert result.returncode == 1, result.stderr
    assert result.stderr.count("stage 'flat'") == 1 and "output 'y'" in result.stderr, result.stderr
    assert "StageFailed" not in result.stderr and "Traceback" not in result.stderr, result.stderr
