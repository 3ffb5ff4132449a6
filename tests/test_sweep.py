"""Sweeps: grids, zips, explicit variants, shared work computed once, resumable, failures isolated; runs, compare."""

import json

import pytest
from conftest import executions, run_cli

from msflow.sweep import STATUS_WIDTH, expand_variants, run_sweep

STAGES = ["src", "scaled", "sign", "csv", "total"]


def test_grid_from_cli_values_and_file(numproject):
    assert expand_variants(["src.n=3,4", "scaled.factor=1,2,3"], None) == [
        {"src.n": n, "scaled.factor": f} for n in (3, 4) for f in (1, 2, 3)
    ]
    from_file = expand_variants([], numproject / "sweep.yaml")
    assert from_file == [
        {"src.n": 3, "scaled.factor": 1},
        {"src.n": 3, "scaled.factor": 2},
        {"src.n": 4, "scaled.factor": 1},
        {"src.n": 4, "scaled.factor": 2},
        {"src.n": 9, "scaled.factor": 5},
    ]
    assert expand_variants(["src.offset=[1],[2]"], None) == [{"src.offset": [1]}, {"src.offset": [2]}]


def test_sweep_computes_each_key_once_and_resumes(numproject, tmp_path, monkeypatch):
    log = tmp_path / "log"
    monkeypatch.setenv("NUMSTAGES_LOG", str(log))
    variants = expand_variants(["src.n=3,4", "scaled.factor=1,2"], None)
    first = run_sweep(numproject / "pipeline.yaml", variants, jobs=2)
    assert all(v.ok for v in first.variants)
    # csv is shared by all four variants; src by two each; every distinct key executed exactly once
    assert first.executed == first.unique_keys == len(executions(log))
    assert executions(log).count("csv") == 1 and executions(log).count("src") == 2
    totals = {(v.params["src.n"], v.params["scaled.factor"]): v.metrics["total"]["total"] for v in first.variants}
    assert totals[(3, 1)] == pytest.approx(2 + 21) and totals[(4, 2)] == pytest.approx(3 + 21)
    again = run_sweep(numproject / "pipeline.yaml", variants)
    assert again.executed == 0 and len(executions(log)) == first.executed
    records = [json.loads(p.read_text()) for p in (numproject / ".msflow" / "runs").glob("*.json")]
    assert len(records) == 8 and all(r["variant"] and r["sweep"] for r in records)


def test_failing_variant_does_not_stop_the_others(numproject):
    variants = expand_variants(["broken.mode=fine,crash,user"], None)
    result = run_sweep(numproject / "broken_sweep.yaml", variants)
    status = {v.params["broken.mode"]: v.ok for v in result.variants}
    assert status == {"fine": True, "crash": False, "user": False}
    crash = next(v for v in result.variants if v.params["broken.mode"] == "crash")
    assert "boom" in crash.error


def test_sweep_table_cuts_long_errors_short_and_lists_them_whole_below(numproject):
    result = run_cli(numproject, "sweep", "broken_sweep.yaml", "-S", "broken.mode=fine,schema,crash", "-q")
    assert result.returncode == 1, result.stderr
    table, below = result.stdout.split("\n\n")
    full = "output 'y': axis 0 has size 4, expected 3 (shape (4,))"
    rows = table.splitlines()
    status = rows[0].index("status")
    assert rows[2][status:].startswith("failed: output 'y': axis 0") and "…" in rows[2] and full not in table
    assert rows[0].index("broken.score") - status == STATUS_WIDTH + 2  # the status column, and two spaces
    assert below.splitlines() == [
        f"variant 2 (broken.mode=schema): {full}",
        "variant 3 (broken.mode=crash): RuntimeError: boom",
    ]
    csv = run_cli(numproject, "sweep", "broken_sweep.yaml", "-S", "broken.mode=fine,schema", "--format", "csv", "-q")
    assert f"failed: {full}" in csv.stdout and "variant 2" not in csv.stdout  # whole in the cell, nothing below


def test_sweep_cli_table_formats_and_sort(numproject):
    result = run_cli(numproject, "sweep", "--grid", "sweep.yaml", "--format", "csv", "--sort", "-total.total", "-q")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0] == "#,src.n,scaled.factor,status,total.total"
    totals = [float(line.split(",")[-1]) for line in lines[1:]]
    assert totals == sorted(totals, reverse=True) and len(totals) == 5
    assert "5 variants" in result.stderr
    md = run_cli(numproject, "sweep", "-S", "src.n=3,4", "--format", "md", "-q")
    assert md.stdout.startswith("| # | src.n |") and "0 stage executions" not in md.stderr
    again = run_cli(numproject, "sweep", "-S", "src.n=3,4", "--format", "json", "-q")
    rows = json.loads(again.stdout)
    assert [r["src.n"] for r in rows] == [3, 4] and "0 stage executions" in again.stderr


def test_sweep_sort_naming_no_stage_fails_before_any_variant_runs(numproject):
    result = run_cli(numproject, "sweep", "--grid", "sweep.yaml", "--sort", "-totl.total")
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        "error: field '--sort': cannot sort by 'totl.total': not a swept parameter (src.n, scaled.factor), and "
        "unknown stage 'totl' (did you mean 'total'?); stages: ['csv', 'scaled', 'sign', 'src', 'total']"
    ]
    assert not (numproject / ".msflow" / "artifacts").exists()


def test_sweep_sort_by_a_misspelt_metric_stops_when_the_stage_first_finishes(numproject, tmp_path, monkeypatch):
    log = tmp_path / "log"
    monkeypatch.setenv("NUMSTAGES_LOG", str(log))
    result = run_cli(numproject, "sweep", "--grid", "sweep.yaml", "--sort", "total.totl", "-q")
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        "error: field '--sort': cannot sort by 'total.totl': stage 'total' gives no metric 'totl' "
        "(did you mean 'total'?); its metrics: total"
    ]
    # each of the 5 variants has its own total: only the first one ran before the sweep stopped
    assert executions(log).count("total") == 1
    listing = run_cli(numproject, "runs").stdout
    assert "STOPPED" in listing


def test_sweep_sort_by_a_metric_shows_it_as_a_column(numproject):
    result = run_cli(numproject, "sweep", "-S", "src.n=3,4", "--metrics", "csv.*", "--sort", "-total.total", "-q")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0].split() == ["#", "src.n", "status", "total.total"]  # csv gives no metrics
    assert [line.split()[0] for line in lines[1:]] == ["2", "1"]


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["-S", "src.nn=3,4"], "unknown parameter 'nn'"),
        (["-S", "nope.n=3,4"], "unknown stage 'nope'"),
        (["-S", "src.n="], "the grid is empty"),
        ([], "the grid is empty"),
        (["-S", "src.n=3,x"], "params.n"),
        (
            ["-S", "src.n=3,4", "--format", "xml"],
            "field '--format': unknown format 'xml'; choose table, md, csv or json",
        ),
    ],
)
def test_sweep_user_errors(numproject, args, fragment):
    result = run_cli(numproject, "sweep", *args)
    assert result.returncode == 2, result.stderr
    assert fragment in result.stderr and "Traceback" not in result.stderr
    assert not (numproject / ".msflow" / "artifacts").exists()


def test_grid_file_errors(numproject):
    (numproject / "bad_grid.yaml").write_text("grid: {src.n: []}\n")
    result = run_cli(numproject, "sweep", "--grid", "bad_grid.yaml")
    assert result.returncode == 2 and "bad_grid.yaml" in result.stderr and "non-empty list" in result.stderr
    (numproject / "bad_grid.yaml").write_text("zip: {src.n: [1, 2], src.offset: [1]}\n")
    assert "one length" in run_cli(numproject, "sweep", "--grid", "bad_grid.yaml").stderr
    (numproject / "bad_grid.yaml").write_text("grids: {}\n")
    assert "unknown key" in run_cli(numproject, "sweep", "--grid", "bad_grid.yaml").stderr


def test_runs_and_compare(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert run_cli(numproject, "run", "-q", "-S", "scaled.factor=7").returncode == 0
    listing = run_cli(numproject, "runs").stdout.strip().splitlines()
    assert len(listing) == 2 and "scaled.factor=7" in listing[1]
    first, second = (line.split()[0] for line in listing)
    diff = run_cli(numproject, "compare", first, second).stdout
    assert "param factor: 3.0 -> 7.0" in diff and "scaled:" in diff
    assert "csv:" not in diff and "stages identical" in diff
    missing = run_cli(numproject, "compare", first, "nope")
    assert missing.returncode == 2 and "no run matches 'nope'; `msflow runs` lists them" in missing.stderr
