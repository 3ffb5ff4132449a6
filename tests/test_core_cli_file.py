"""Every command takes its pipeline file the same way: as its last argument FILE, or as -f/--file FILE."""

import typer
from conftest import run_cli
from typer.testing import CliRunner

from msflow.commands import app

#: each command with the pipeline file as "FILE", the arguments it needs besides (RUN_A/RUN_B: two run ids)
COMMANDS = {
    "run": ["run", "FILE", "-q"],
    "status": ["status", "FILE"],
    "why": ["why", "total", "FILE"],
    "dag": ["dag", "FILE"],
    "show": ["show", "total", "FILE"],
    "export": ["export", "total.total", "out.npy", "FILE"],
    "gc": ["gc", "FILE", "--dry-run"],
    "verify": ["verify", "FILE"],
    "sweep": ["sweep", "FILE", "-S", "src.n=3,4", "-q"],
    "runs": ["runs", "FILE"],
    "compare": ["compare", "RUN_A", "RUN_B", "FILE"],
    "report": ["report", "FILE", "-o", "report.html"],
}


def test_every_command_declares_the_file_argument_last_and_the_file_option():
    commands = typer.main.get_command(app).commands
    assert set(commands) == set(COMMANDS)  # a new command joins COMMANDS, and so this test
    for name, command in commands.items():
        params = {p.name: p for p in command.params}
        positional = [p.name for p in command.params if p.param_type_name == "argument"]
        assert positional[-1] == "file" and not params["file"].required, name
        assert params["file_option"].opts == ["-f", "--file"], name


def test_every_command_reads_the_pipeline_file_given_either_way(numproject, monkeypatch):
    (numproject / "pipeline.yaml").rename(numproject / "other.yaml")  # the default file is no fallback
    assert run_cli(numproject, "run", "other.yaml", "-q").returncode == 0
    assert run_cli(numproject, "run", "-f", "other.yaml", "-q", "-S", "scaled.factor=7").returncode == 0
    run_a, run_b = (line.split()[0] for line in run_cli(numproject, "runs", "other.yaml").stdout.splitlines())
    monkeypatch.chdir(numproject)  # the commands themselves in this process: 24 of them, a second saved on each
    runner, failed = CliRunner(), []
    for args in COMMANDS.values():
        args = [{"RUN_A": run_a, "RUN_B": run_b}.get(a, a) for a in args]
        as_argument = ["other.yaml" if a == "FILE" else a for a in args]
        as_option = [a for a in args if a != "FILE"] + ["-f", "other.yaml"]
        for form in (as_argument, as_option):
            result = runner.invoke(app, form)
            if result.exit_code != 0:
                failed.append((form, result.output, result.exception))
    assert not failed


def test_two_different_pipeline_files_are_a_user_error(numproject):
    result = run_cli(numproject, "status", "pipeline.yaml", "-f", "sweep.yaml")
    assert result.returncode == 2
    assert result.stderr == "error: field 'FILE': two pipeline files, pipeline.yaml and -f sweep.yaml: give one\n"
    same = run_cli(numproject, "status", "pipeline.yaml", "--file", "./pipeline.yaml")
    assert same.returncode == 0, same.stderr


def test_the_no_op_fast_path_takes_the_file_option_too(numproject, monkeypatch):
    import os

    from msflow.fastpath import parse_args

    monkeypatch.chdir(numproject)
    path = os.path.abspath("pipeline.yaml")
    assert parse_args(["run", "-f", "pipeline.yaml", "-q"]) == ("run", path, [], True)
    assert parse_args(["status", "--file=pipeline.yaml", "-S", "src.n=3"]) == ("status", path, ["src.n=3"], False)
    assert parse_args(["run", "pipeline.yaml", "-f", "pipeline.yaml"]) is None  # twice: the full path decides
