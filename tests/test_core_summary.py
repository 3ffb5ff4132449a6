"""The pipeline's ``summary:``: stage metrics printed when a run ends, on the full path and the no-op fast path
alike; checked stage names; the default columns of a sweep."""

import json

from conftest import run_cli

from msflow.summary import format_metric, summary_lines


def with_summary(proj, entries):
    path = proj / "pipeline.yaml"
    path.write_text(path.read_text() + "summary:\n" + "".join(f"  - '{e}'\n" for e in entries))


def newest_record(proj):
    return json.loads(sorted((proj / ".msflow" / "runs").glob("*.json"))[-1].read_text())


def parsed(stdout):
    return [tuple(line.split()) for line in stdout.splitlines()]


def test_a_run_prints_the_summary_on_stdout_and_a_no_op_run_prints_the_same(numproject):
    with_summary(numproject, ["total.total", "src.*"])
    first = run_cli(numproject, "run", "-q")
    assert first.returncode == 0, first.stderr
    stages = newest_record(numproject)["stages"]
    expected = [("total.total", format_metric(stages["total"]["metrics"]["total"])), ("src.n", "6")]
    assert parsed(first.stdout) == expected
    assert first.stdout.splitlines()[1].startswith("src.n        ")  # names aligned

    noop = run_cli(numproject, "run", "-q")
    assert noop.returncode == 0 and noop.stdout == first.stdout
    assert "same_as" in newest_record(numproject)  # answered by the fast path, from the saved state
    loud = run_cli(numproject, "run")
    assert loud.stdout == first.stdout and "5 cached" in loud.stderr  # progress on stderr, the result on stdout

    other = run_cli(numproject, "run", "-q", "-S", "src.n=4")
    assert other.returncode == 0 and ("src.n", "4") in parsed(other.stdout)


def test_a_name_that_is_no_metric_is_a_warning_that_lists_them(numproject):
    with_summary(numproject, ["src.count", "src.count_*", "total.total"])
    result = run_cli(numproject, "run", "-q")
    assert result.returncode == 0, result.stderr
    warning = "warning: summary: 'src.count' is no metric of stage 'src' (its metrics: n)"
    assert warning in result.stderr and [name for name, _ in parsed(result.stdout)] == ["total.total"]
    assert "count_*" not in result.stderr  # a pattern may match none (metrics only some data give)
    assert warning in run_cli(numproject, "run", "-q").stderr  # the no-op path says it too


def test_summary_entries_name_known_stages_or_nothing_runs(numproject):
    log = numproject / "log"
    for entries, message in [
        (["totl.total"], "summary.0': 'totl.total': no stage 'totl' (did you mean 'total'?)"),
        (["src.n", "total"], "summary.1': 'total' is not stage.metric"),
    ]:
        with_summary(numproject, entries)
        result = run_cli(numproject, "run", "-q", env={"NUMSTAGES_LOG": str(log)})
        assert result.returncode == 2 and "pipeline.yaml" in result.stderr and message in result.stderr, result.stderr
        assert "Traceback" not in result.stderr and not log.exists()
        (numproject / "pipeline.yaml").write_text((numproject / "pipeline.yaml").read_text().split("summary:")[0])


def test_one_entry_may_be_written_without_a_list(numproject):
    (numproject / "pipeline.yaml").write_text((numproject / "pipeline.yaml").read_text() + "summary: src.n\n")
    result = run_cli(numproject, "run", "-q")
    assert result.returncode == 0 and parsed(result.stdout) == [("src.n", "6")], result.stderr


def test_a_sweep_tabulates_the_summary_unless_told_otherwise(numproject):
    # scaled.factor changes no metric: without a summary the table has no metric column
    plain = run_cli(numproject, "sweep", "-S", "scaled.factor=3,4", "--format", "csv", "-q")
    assert plain.returncode == 0 and plain.stdout.splitlines()[0] == "#,scaled.factor,status", plain.stdout
    with_summary(numproject, ["src.n", "total.*"])
    table = run_cli(numproject, "sweep", "-S", "scaled.factor=3,4", "--format", "csv", "-q")
    assert table.stdout.splitlines()[0] == "#,scaled.factor,status,src.n,total.total", table.stdout
    chosen = run_cli(numproject, "sweep", "-S", "scaled.factor=3,4", "--format", "csv", "-q", "--metrics", "src.n")
    assert chosen.stdout.splitlines()[0] == "#,scaled.factor,status,src.n"


def test_summary_lines_order_once_each_and_only_finished_stages():
    stages = {
        "a": {"state": "ran", "metrics": {"err": 0.0123456, "n": 3, "hist": [1, 2]}},
        "b": {"state": "cached", "metrics": {"ok": True, "bad": float("nan")}},
        "c": {"state": "failed", "metrics": {}},
    }
    lines, warnings = summary_lines(["b.*", "a.err", "a.*", "c.x", "gone.x", "a.none_*"], stages)
    assert [tuple(line.split(None, 1)) for line in lines] == [
        ("b.bad", "nan"),
        ("b.ok", "true"),
        ("a.err", "0.01235"),
        ("a.hist", "[1, 2]"),
        ("a.n", "3"),
    ]
    assert warnings == []  # a failed or absent stage is the run's own report, not the summary's
    assert format_metric(list(range(100))).endswith("...") and len(format_metric(list(range(100)))) == 80


def test_a_run_report_opens_with_the_summary(numproject, tmp_path):
    with_summary(numproject, ["src.n"])
    assert run_cli(numproject, "run", "-q").returncode == 0
    page = tmp_path / "report.html"
    assert run_cli(numproject, "report", "-o", page).returncode == 0
    html = page.read_text()
    assert "<h2>Summary</h2>" in html and "<tr><td>src.n</td><td>6</td></tr>" in html
    assert html.index("<h2>Summary</h2>") < html.index("<h2>Stage graph</h2>")
    (numproject / "pipeline.yaml").write_text((numproject / "pipeline.yaml").read_text().split("summary:")[0])
    assert run_cli(numproject, "report", "-o", page).returncode == 0
    assert "<h2>Summary</h2>" not in page.read_text()  # none without a summary:
