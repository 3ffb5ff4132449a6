"""The inspection commands: status, why, dag, show, export, compare, gc; publish; the Python API."""

import json
import re
import shutil

import numpy as np
import pytest
from conftest import run_cli

import msflow


def test_status_lists_what_would_run_and_why(numproject):
    fresh = run_cli(numproject, "status")
    assert fresh.returncode == 0
    assert (
        "src" in fresh.stdout
        and "never run" in fresh.stdout
        and "0 cached, 2 to run, 3 waiting on them" in fresh.stdout
    )
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert "5 cached, 0 to run" in run_cli(numproject, "status").stdout
    changed = run_cli(numproject, "status", "-S", "src.n=4")
    assert "param n: 6 -> 4" in changed.stdout
    assert "upstream src must run first" in changed.stdout
    runs = numproject / ".msflow" / "runs"
    before = sorted(runs.glob("*.json"))
    run_cli(numproject, "status")
    assert sorted(runs.glob("*.json")) == before  # status computes keys but records no run


def test_why_names_the_changed_code_file_param_and_input(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert "up to date" in run_cli(numproject, "why", "scaled").stdout
    param = run_cli(numproject, "why", "scaled", "-S", "scaled.factor=7")
    assert "param factor: 3.0 -> 7.0" in param.stdout
    helper = numproject / "numstages" / "helpers.py"
    helper.write_text(helper.read_text() + "\nEXTRA = 1\n")
    code = run_cli(numproject, "why", "scaled")
    assert "code: numstages/helpers.py changed" in code.stdout
    assert "up to date" in run_cli(numproject, "why", "csv").stdout  # csv does not import helpers
    (numproject / "data" / "table.csv").write_text("9,9,9\n")
    data = run_cli(numproject, "why", "csv")
    assert "input table: data file content changed: data/table.csv" in data.stdout
    assert run_cli(numproject, "run", "-q").returncode == 0
    after = run_cli(numproject, "why", "total", "-S", "src.offset=2")
    assert "upstream sign must run first" in after.stdout or "upstream" in after.stdout
    unknown = run_cli(numproject, "why", "nope")
    assert unknown.returncode == 2 and "unknown stage 'nope'" in unknown.stderr


def test_dag_text_mermaid_and_dot(numproject):
    text = run_cli(numproject, "dag").stdout
    assert text.index("src") < text.index("scaled") < text.index("total")
    mermaid = run_cli(numproject, "dag", "--mermaid").stdout
    assert mermaid.startswith("graph TD") and "s_src -->|x → x| s_scaled" in mermaid
    dot = run_cli(numproject, "dag", "--dot").stdout
    assert dot.startswith("digraph") and '"sign" -> "total"' in dot


def test_show_stage_and_output(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    shown = run_cli(numproject, "show", "src")
    assert shown.returncode == 0
    assert "x" in shown.stdout and "float64" in shown.stdout and "(6,)" in shown.stdout
    assert "min 0 max 5 mean 2.5" in shown.stdout and '"n": 6' in shown.stdout and "n = 6" in shown.stdout
    one = run_cli(numproject, "show", "src.x")
    assert "[0. 1. 2. 3. 4. 5.]" in one.stdout
    missing = run_cli(numproject, "show", "src.y")
    assert missing.returncode == 2 and "no output 'y'" in missing.stderr


def test_show_before_any_run_is_a_clear_error(numproject):
    result = run_cli(numproject, "show", "src")
    assert result.returncode == 2 and "no artifact in the store yet" in result.stderr


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".csv", ".json"])
def test_export_formats_round_trip(numproject, suffix):
    assert run_cli(numproject, "run", "-q").returncode == 0
    dest = numproject / "out" / f"x{suffix}"
    result = run_cli(numproject, "export", "scaled.y", dest)
    assert result.returncode == 0, result.stderr
    expected = np.arange(6.0) * 3
    if suffix == ".npy":
        got = np.load(dest, allow_pickle=False)
    elif suffix == ".npz":
        got = np.load(dest, allow_pickle=False)["y"]
    elif suffix == ".csv":
        lines = dest.read_text().splitlines()
        assert lines[0] == "y"
        got = np.array([float(v) for v in lines[1:]])
    else:
        got = np.array(json.loads(dest.read_text())["data"])
    assert np.allclose(got, expected)


def test_export_unknown_format_is_a_user_error(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    result = run_cli(numproject, "export", "scaled.y", numproject / "x.xlsx")
    assert result.returncode == 2 and "unsupported export format" in result.stderr


def test_export_of_a_stage_writes_its_only_output_or_all_of_several_into_a_npz(numproject, tmp_path):
    """`export STAGE FILE`: src has one output, written in any format; slow has two, written together into a
    .npz; any other file for slow is an error that lists its outputs and shows STAGE.OUTPUT."""
    assert run_cli(numproject, "run", "-q").returncode == 0
    one = run_cli(numproject, "export", "src", tmp_path / "x.csv")
    assert one.returncode == 0 and "(src.x, current)" in one.stderr, one.stderr
    assert one.stdout == "" and (tmp_path / "x.csv").read_text().splitlines() == ["x", "0", "1", "2", "3", "4", "5"]
    (numproject / "two.yaml").write_text("version: 1\nstages:\n  slow:\n    uses: numstages.basic:Slow\n"
                                         "    params: {size: 5}\n")  # fmt: skip
    made = msflow.run(numproject / "two.yaml")
    both = run_cli(numproject, "export", "slow", tmp_path / "s.npz", "-f", "two.yaml")
    assert both.returncode == 0 and "(the 2 outputs of slow, current)" in both.stderr, both.stderr
    with np.load(tmp_path / "s.npz", allow_pickle=False) as saved:
        assert sorted(saved) == ["big", "small"]
        assert all(np.array_equal(saved[name], made.load(f"slow.{name}")) for name in saved)
    csv = run_cli(numproject, "export", "slow", tmp_path / "s.csv", "-f", "two.yaml")
    expected = (
        "error: field 'STAGE.output': stage 'slow' has 2 outputs (big, small): write STAGE.OUTPUT (e.g. slow.big), "
        "or give a .npz file to hold them all\n"
    )
    assert csv.returncode == 2 and csv.stderr == expected and not (tmp_path / "s.csv").exists(), csv.stderr


def test_a_stage_with_file_outputs_is_never_exported_whole_into_a_npz(tmp_path):
    """A file output holds a file of its own format (GLB, MP4): a .npz of the stage would bury it as bytes."""
    from msflow.artifact import ArtifactView
    from msflow.errors import UserError
    from msflow.exporting import export_outputs

    manifest = {"outputs": {"animation": {"file_suffix": ".glb"}, "weights": {}}}
    view = ArtifactView({"animation": np.zeros(3, np.uint8), "weights": np.ones(2)}, {}, {}, manifest=manifest)
    with pytest.raises(UserError, match=r"file outputs among them \(animation\): write STAGE.OUTPUT \(e.g. "):
        export_outputs(view, "export", tmp_path / "all.npz")
    assert not (tmp_path / "all.npz").exists()


def test_a_run_id_that_matches_no_run_or_several_says_what_to_do(numproject):
    for n in (3, 4):
        assert run_cli(numproject, "run", "-q", "-S", f"src.n={n}").returncode == 0
    none = run_cli(numproject, "compare", "nope", "nada")
    assert none.returncode == 2 and "no run matches 'nope'; `msflow runs` lists them" in none.stderr, none.stderr
    year = run_cli(numproject, "compare", "2", "2")
    assert year.returncode == 2 and "'2' matches 2 runs (" in year.stderr and "give more of the id" in year.stderr


def test_compare_takes_metrics_equal_to_the_last_bits_as_equal_and_prints_numbers_compactly(numproject):
    """Run A sums the table 0.1 + 0.2, run B reads 0.3, run C 0.1234567891234 (src.n=1: the total is the table's
    sum). A and B differ in keys but their totals only in the last bit (0.30000000000000004 against 0.3): that is
    no metric change. A and C differ for real: said with 6 significant digits and the change."""
    table = numproject / "data" / "table.csv"
    ids = []
    for content in ("0.1,0.2\n", "0.3\n", "0.1234567891234\n"):
        table.write_text(content)
        assert run_cli(numproject, "run", "-q", "-S", "src.n=1").returncode == 0
        ids.append(sorted((numproject / ".msflow" / "runs").glob("*.json"))[-1].stem)
    close = run_cli(numproject, "compare", ids[0], ids[1])
    assert close.returncode == 0, close.stderr
    assert "csv:\n  key " in close.stdout and "total:\n  key " in close.stdout, close.stdout  # keys: exact
    assert "metric" not in close.stdout.split("stages identical")[0], close.stdout
    assert "1 metric value differs only within the tolerance (rtol 1e-9, atol 1e-12)" in close.stdout
    apart = run_cli(numproject, "compare", ids[0], ids[2])
    assert "  metric total: 0.3 -> 0.123457 (-0.1765, -58.8%)" in apart.stdout.splitlines(), apart.stdout
    assert "0.30000000000000004" not in apart.stdout + close.stdout and "within" not in apart.stdout


def test_gc_keeps_recent_runs_and_drops_the_rest(numproject):
    for n in (3, 4, 5):
        assert run_cli(numproject, "run", "-q", "-S", f"src.n={n}").returncode == 0
    before = len(list((numproject / ".msflow" / "artifacts").glob("*/*")))
    dry = run_cli(numproject, "gc", "--keep-runs", "1", "--dry-run")
    assert "would remove" in dry.stdout
    assert len(list((numproject / ".msflow" / "artifacts").glob("*/*"))) == before
    result = run_cli(numproject, "gc", "--keep-runs", "1")
    assert result.returncode == 0
    after = len(list((numproject / ".msflow" / "artifacts").glob("*/*")))
    assert after < before
    latest = msflow.run(numproject / "pipeline.yaml", overrides=["src.n=5"])
    assert latest.executed == []  # the newest run's artifacts were kept
    older = msflow.run(numproject / "pipeline.yaml", overrides=["src.n=3"])
    assert "src" in older.executed


def folder_bytes(folder):
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def said_bytes(text):
    """The bytes a size as gc prints it stands for (``12.3 kB``), and the rounding it allows."""
    value, unit = re.search(r"\(([\d.]+) (B|kB|MB|GB)", text).groups()
    scale = {"B": 1, "kB": 1e3, "MB": 1e6, "GB": 1e9}[unit]
    return float(value) * scale, 0.05 * scale


def test_gc_counts_the_artifacts_the_store_holds_and_the_bytes_it_freed(numproject):
    """The newest run's total is gone from the store already (as `msflow verify --delete` leaves it): gc counts
    the artifacts it keeps in the store, not the keys the runs it keeps name, and the bytes of what it removed."""
    for n in (3, 4, 5):
        assert run_cli(numproject, "run", "-q", "-S", f"src.n={n}").returncode == 0
    newest = sorted((numproject / ".msflow" / "runs").glob("*.json"))[-1]
    key = json.loads(newest.read_text())["stages"]["total"]["key"]
    artifacts = numproject / ".msflow" / "artifacts"
    shutil.rmtree(artifacts / key[:2] / key)
    before = {p.name: folder_bytes(p) for p in artifacts.glob("*/*")}

    dry = run_cli(numproject, "gc", "--keep-runs", "1", "--dry-run")
    assert {p.name for p in artifacts.glob("*/*")} == set(before)
    done = run_cli(numproject, "gc", "--keep-runs", "1")
    assert done.returncode == 0, done.stderr
    after = {p.name for p in artifacts.glob("*/*")}
    removed = set(before) - after
    assert len(after) == 4 and len(removed) == len(before) - 4  # src, scaled, sign, csv of the newest run
    said = f"removed {len(removed)} artifacts ("
    assert done.stdout.startswith(said) and f"kept {len(after)} artifacts, cleared 0" in done.stdout, done.stdout
    shown, rounding = said_bytes(done.stdout)
    assert abs(shown - sum(before[k] for k in removed)) <= rounding and "freed" in done.stdout, done.stdout
    size = done.stdout.split("(")[1].split(" freed")[0]  # a dry run tells the same, clearing nothing
    assert dry.stdout == f"would remove {len(removed)} artifacts ({size}), would keep {len(after)} artifacts\n", (
        dry.stdout
    )


def test_publish_materialises_outputs_after_each_run(numproject):
    text = (numproject / "pipeline.yaml").read_text()
    (numproject / "pipeline.yaml").write_text(text + "publish:\n  scaled.y: results/scaled.csv\n")
    assert run_cli(numproject, "run", "-q").returncode == 0
    target = numproject / "results" / "scaled.csv"
    assert target.read_text().splitlines()[1:3] == ["0", "3"]
    target.unlink()
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert target.exists()  # republished when missing


def test_python_api_returns_numpy_artifacts(numproject):
    result = msflow.run(numproject / "pipeline.yaml", overrides=["src.n=3"])
    assert result.ok and isinstance(result.load("src.x"), np.ndarray)
    view = result.artifact("total")
    assert view.metrics["total"] == pytest.approx(float(view["total"]))
    assert result.metrics["src"] == {"n": 3}
