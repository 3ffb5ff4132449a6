"""Integrity on read, and a no-op that stays cheap: each behaviour checked across separate processes (a memo or
a state that only lives in one process would pass in-process tests and fail users)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from conftest import cli_env, run_cli

import msflow
from msflow.cli import main


def lock_keys(proj, name="pipeline.lock"):
    return {s: e["key"] for s, e in yaml.safe_load((proj / name).read_text())["stages"].items()}


def artifact_dir(proj, key):
    return proj / ".msflow" / "artifacts" / key[:2] / key


def flip_a_byte(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x40
    path.write_bytes(bytes(data))


def damage(folder, probe):
    """The four probes of issue 15: a flipped byte in a chunk, a deleted chunk, a truncated manifest, an
    emptied artifact folder."""
    chunk = folder / "x" / "c" / "0"
    if probe == "flip_byte":
        flip_a_byte(chunk)
    elif probe == "delete_chunk":
        chunk.unlink()
    elif probe == "truncate_manifest":
        manifest = folder / "zarr.json"
        manifest.write_bytes(manifest.read_bytes()[:40])
    else:
        for entry in folder.iterdir():
            __import__("shutil").rmtree(entry) if entry.is_dir() else entry.unlink()


PROBES = ["flip_byte", "delete_chunk", "truncate_manifest", "empty_folder"]


@pytest.mark.parametrize("probe", PROBES)
def test_a_corrupt_artifact_is_caught_by_show_export_and_run_which_repairs_it(
    numproject, tmp_path, monkeypatch, capsys, probe
):
    msflow.run(numproject / "pipeline.yaml")
    key = lock_keys(numproject)["src"]
    damage(artifact_dir(numproject, key), probe)

    for args in (["show", "src.x"], ["export", "src.x", tmp_path / "x.npy"]):
        code, _, err = cli(numproject, monkeypatch, capsys, *args)
        assert code == 1, (args, err)
        assert key in err and "msflow verify" in err and "Traceback" not in err
    assert not (tmp_path / "x.npy").exists() and list(tmp_path.glob(".x.npy*")) == []

    # a run that reads it (scaled reruns with a new factor) moves it aside and recomputes it
    run = run_cli(numproject, "run", "-q", "-S", "scaled.factor=5")
    assert run.returncode == 0, run.stderr
    assert f"its artifact {key[:12]} was corrupt" in run.stderr and "Traceback" not in run.stderr
    aside = list((numproject / ".msflow" / "corrupt").glob(f"{key}.*"))
    assert len(aside) == 2  # the artifact folder, kept for inspection, and the reason beside it
    out = msflow.run(numproject / "pipeline.yaml", ["scaled.factor=5"])
    assert out.executed == [] and np.array_equal(out.load("src.x"), np.arange(6.0))
    assert np.array_equal(out.load("scaled.y"), 5 * np.arange(6.0))
    assert all(out.session.store.verify(k) == [] for k in out.session.store.keys())
    records = [json.loads(p.read_text()) for p in (numproject / ".msflow" / "runs").glob("*.json")]
    (repair,) = [r for record in records for r in record.get("repairs", [])]
    assert repair["key"] == key and repair["stage"] == "src"


def test_gc_clears_the_damaged_artifacts_runs_set_aside(numproject):
    """A run sets a damaged artifact aside for inspection; gc, which promises to clear what runs leave behind,
    deletes it with its reason (a dry run only names it), and what the run recomputed stays."""
    msflow.run(numproject / "pipeline.yaml")
    key = lock_keys(numproject)["src"]
    flip_a_byte(artifact_dir(numproject, key) / "x" / "c" / "0")
    assert run_cli(numproject, "run", "-q", "-S", "scaled.factor=5").returncode == 0  # reads src
    aside = numproject / ".msflow" / "corrupt"
    assert len(list(aside.iterdir())) == 2
    dry = run_cli(numproject, "gc", "--dry-run")
    assert dry.returncode == 0 and "would remove 1 damaged artifact set aside" in dry.stdout, dry.stdout
    assert len(list(aside.iterdir())) == 2
    done = run_cli(numproject, "gc")
    assert done.returncode == 0 and "removed 1 damaged artifact set aside" in done.stdout, done.stdout
    assert list(aside.iterdir()) == []
    again = run_cli(numproject, "gc")
    assert "damaged" not in again.stdout, again.stdout
    out = msflow.run(numproject / "pipeline.yaml")
    assert out.executed == [] and np.array_equal(out.load("src.x"), np.arange(6.0))


def test_status_reads_manifests_but_no_data(numproject):
    msflow.run(numproject / "pipeline.yaml")
    keys = lock_keys(numproject)
    damage(artifact_dir(numproject, keys["src"]), "flip_byte")
    damage(artifact_dir(numproject, keys["csv"]), "truncate_manifest")
    status = run_cli(numproject, "status")
    assert status.returncode == 0 and "Traceback" not in status.stderr
    assert "src     cached" in status.stdout and "csv     will run" in status.stdout
    assert "its artifact is corrupt" in status.stdout, status.stdout


def test_a_no_op_run_repairs_a_truncated_manifest_and_verify_reports_chunk_damage(numproject):
    msflow.run(numproject / "pipeline.yaml")
    keys = lock_keys(numproject)
    manifest = artifact_dir(numproject, keys["total"]) / "zarr.json"
    manifest.write_bytes(manifest.read_bytes()[:-7])
    flip_a_byte(artifact_dir(numproject, keys["scaled"]) / "y" / "c" / "0")  # read by no stage that runs
    run = run_cli(numproject, "run", "-q")  # reads every manifest: the truncated one is caught
    assert run.returncode == 0 and "was corrupt" in run.stderr, run.stderr
    verify = run_cli(numproject, "verify")  # the flipped byte is only found by reading the data
    assert verify.returncode == 1 and f"corrupt {keys['scaled']}" in verify.stdout, verify.stdout


# ------------------------------------------------------------------------------------------------ publishing
def test_publish_dir_is_the_explicit_way_to_publish_outside_the_project(numproject, tmp_path):
    text = (numproject / "pipeline.yaml").read_text()
    (numproject / "pipeline.yaml").write_text(text + "publish:\n  scaled.y: scaled.npy\n")
    outside = tmp_path / "elsewhere"
    result = run_cli(numproject, "run", "-q", "--publish-dir", outside)
    assert result.returncode == 0, result.stderr
    assert np.array_equal(np.load(outside / "scaled.npy"), 3 * np.arange(6.0))
    assert not (numproject / "scaled.npy").exists()
    assert run_cli(numproject, "run", "-q").returncode == 0 and (numproject / "scaled.npy").is_file()


# ------------------------------------------------------------------------------------------------ memo and no-ops
def test_a_second_process_does_not_reread_an_unchanged_data_file(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    data = numproject / "data" / "table.csv"
    st = data.stat()
    text = data.read_text()
    data.write_text(text.replace("1", "7", 1))  # same size, new content ...
    os.utime(data, ns=(st.st_atime_ns, st.st_mtime_ns))  # ... and the old mtime: only a reread could tell
    assert data.stat().st_ino == st.st_ino
    fast_state = numproject / ".msflow" / "cache" / "fast"
    for state in fast_state.iterdir():
        state.unlink()  # answer through the full path, from the memo saved by the first process
    status = run_cli(numproject, "status")
    assert status.returncode == 0 and "5 cached, 0 to run" in status.stdout, status.stdout
    memo = numproject / ".msflow" / "cache" / "memo.json"
    assert str(data) in json.loads(memo.read_text())["data"]
    assert '"dirty"' not in memo.read_text()
    memo.unlink()  # without the memo the file is reread and the change is seen: the check above can fail
    status = run_cli(numproject, "status")
    assert "csv     will run" in status.stdout and "data file content changed" in status.stdout, status.stdout


def test_writing_the_lock_keeps_the_package_scan(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    memo = numproject / ".msflow" / "cache" / "memo.json"
    before = json.loads(memo.read_text())["code"]["dists"]
    lock = (numproject / "pipeline.lock").read_text()
    assert run_cli(numproject, "run", "-q", "-S", "src.n=4").returncode == 0  # rewrites pipeline.lock
    assert (numproject / "pipeline.lock").read_text() != lock
    after = json.loads(memo.read_text())["code"]["dists"]
    assert after["sig"] == before["sig"] and after["map"] == before["map"]


def noop_in_a_fresh_process(proj, *args):
    code = (
        "import sys; from msflow.cli import main; code = main(sys.argv[1:]); "
        "print(' '.join(m for m in ('pydantic', 'typer', 'yaml', 'numpy', 'zarr', 'numstages') if m in sys.modules)); "
        "sys.exit(code)"
    )
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)], cwd=proj, env=cli_env(), capture_output=True, text=True
    )


def test_a_no_op_is_answered_without_pydantic_or_typer_and_writes_a_small_record(numproject):
    first = run_cli(numproject, "run", "warnings.yaml")
    assert first.returncode == 0 and "warning: careful:" in first.stderr, first.stderr
    runs = numproject / ".msflow" / "runs"
    full = list(runs.glob("*.json"))
    noop = noop_in_a_fresh_process(numproject, "run", "warnings.yaml")
    assert noop.returncode == 0, noop.stderr
    assert noop.stdout.strip() == ""  # no heavy module imported
    assert "1 cached in" in noop.stderr and "(cached result)" in noop.stderr  # warnings of cached stages still shown
    assert [line for line in first.stderr.splitlines() if line.startswith("warning")] == [
        line.replace(" (cached result)", "") for line in noop.stderr.splitlines() if line.startswith("warning")
    ]
    (small,) = set(runs.glob("*.json")) - set(full)
    assert small.stat().st_size < 1000 and json.loads(small.read_text())["same_as"] == full[0].stem
    listed = run_cli(numproject, "runs", "warnings.yaml")
    assert listed.returncode == 0 and small.stem in listed.stdout
    status = noop_in_a_fresh_process(numproject, "status", "warnings.yaml")
    assert status.returncode == 0 and status.stdout.splitlines()[-2:] == ["1 cached, 0 to run", ""]


def test_the_fast_path_falls_back_on_any_doubt(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert noop_in_a_fresh_process(numproject, "run", "-q").stdout.strip() == ""
    # an edited helper module: the full path finds that 'scaled' must rerun
    helpers = numproject / "numstages" / "helpers.py"
    helpers.write_text(helpers.read_text().replace("2 * np.asarray(x)", "np.asarray(x) * 2.0"))
    edited = noop_in_a_fresh_process(numproject, "run", "-q")
    assert edited.returncode == 0 and "pydantic" in edited.stdout
    assert noop_in_a_fresh_process(numproject, "run", "-q").stdout.strip() == ""  # a fresh state was saved
    # a deleted artifact, options it does not know, another override: the full path answers
    __import__("shutil").rmtree(artifact_dir(numproject, lock_keys(numproject)["total"]))
    rerun = run_cli(numproject, "run")
    assert rerun.returncode == 0 and "4 cached, 1 ran" in rerun.stderr, rerun.stderr
    for args in (["run", "-q", "--until", "src"], ["run", "-q", "-S", "src.n=3"], ["status", "-S", "src.n=4"]):
        assert "pydantic" in noop_in_a_fresh_process(numproject, *args).stdout, args


def test_a_no_op_writes_a_small_record_only_when_nothing_ran(numproject):
    first = msflow.run(numproject / "pipeline.yaml")
    again = msflow.run(numproject / "pipeline.yaml")
    runs = numproject / ".msflow" / "runs"
    raw = json.loads((runs / f"{again.run_id}.json").read_text())
    assert raw["same_as"] == first.run_id and "stages" not in raw
    expanded = again.session.store.read_run(again.run_id)
    assert expanded["stages"]["src"]["state"] == "cached" and expanded["id"] == again.run_id
    changed = msflow.run(numproject / "pipeline.yaml", ["scaled.factor=4"])
    assert "stages" in json.loads((runs / f"{changed.run_id}.json").read_text())  # something ran: a full record


# ------------------------------------------------------------------------------------------------ small things
def test_reprs_are_compact(numproject):
    result = msflow.run(numproject / "pipeline.yaml")
    for value in (result, result.session, result.states["src"], result.artifact("src")):
        assert len(repr(value)) < 200, repr(value)
    assert "5 ran" in repr(result)


def cli(proj, monkeypatch, capsys, *args):
    """The command line in this process (for behaviour that does not depend on a fresh process)."""
    monkeypatch.chdir(proj)
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_show_and_export_take_overrides(numproject, tmp_path, monkeypatch, capsys):
    msflow.run(numproject / "pipeline.yaml", ["src.n=3"])
    msflow.run(numproject / "pipeline.yaml")
    code, shown, _ = cli(numproject, monkeypatch, capsys, "show", "src.x", "-S", "src.n=3")
    assert code == 0 and "(3,)" in shown and "(current)" in shown, shown
    code, _, _ = cli(numproject, monkeypatch, capsys, "export", "src.x", tmp_path / "x.npy", "-S", "src.n=3")
    assert code == 0 and np.load(tmp_path / "x.npy").shape == (3,)
    assert "(6,)" in cli(numproject, monkeypatch, capsys, "show", "src.x")[1]


def test_gc_keeps_the_report_figures_of_kept_runs(numproject, tmp_path, monkeypatch, capsys):
    (numproject / "figs.yaml").write_text("version: 1\nstages:\n  pic:\n    uses: numstages.basic:Pictured\n")
    msflow.run(numproject / "figs.yaml")
    code, _, err = cli(
        numproject, monkeypatch, capsys, "report", "-f", "figs.yaml", "-o", tmp_path / "a.html", "-j", "1"
    )
    assert code == 0 and "1 rendered" in err, err
    code, out, _ = cli(numproject, monkeypatch, capsys, "gc", "figs.yaml", "--keep-runs", "1")
    assert code == 0 and "removed 0 artifacts" in out, out
    code, _, err = cli(
        numproject, monkeypatch, capsys, "report", "-f", "figs.yaml", "-o", tmp_path / "b.html", "-j", "1"
    )
    assert code == 0 and "0 rendered" in err, err
    msflow.run(numproject / "figs.yaml", ["pic.size=3"])
    code, out, _ = cli(numproject, monkeypatch, capsys, "gc", "figs.yaml", "--keep-runs", "1")
    assert "removed 2 artifacts" in out, out  # the old stage and its figure go


def test_a_damaged_run_record_is_passed_over_by_runs_and_report_and_named_elsewhere(numproject, tmp_path):
    """A run record that is not JSON (damaged, or edited by hand) hides nothing else: ``msflow runs`` lists it as
    unreadable beside the others, ``msflow report`` reports the newest readable run, and a command asked for that
    run says which file it is (exit 1), never a JSON traceback."""
    assert run_cli(numproject, "run", "-q").returncode == 0
    assert run_cli(numproject, "run", "-q", "-S", "scaled.factor=4").returncode == 0
    first, damaged = sorted((numproject / ".msflow" / "runs").glob("*.json"))[-2:]
    damaged.write_text("{trunc")
    listed = run_cli(numproject, "runs")
    assert listed.returncode == 0 and f"{damaged.stem}  UNREADABLE" in listed.stdout and first.stem in listed.stdout
    report = run_cli(numproject, "report", "-o", tmp_path / "r.html")
    assert report.returncode == 0 and first.stem in (tmp_path / "r.html").read_text()
    compared = run_cli(numproject, "compare", first.stem, damaged.stem)
    assert compared.returncode == 1 and "Traceback" not in compared.stderr
    assert f"{damaged.name} is unreadable" in compared.stderr and "delete the file" in compared.stderr


def test_a_damaged_sweep_record_is_named(numproject, tmp_path):
    swept = run_cli(numproject, "sweep", "-S", "src.n=3,4", "-q")
    (record,) = (numproject / ".msflow" / "sweeps").glob("*.json")
    record.write_text("[1, 2")
    report = run_cli(numproject, "report", record.stem, "-o", tmp_path / "s.html")
    assert swept.returncode == 0 and report.returncode == 1 and "Traceback" not in report.stderr
    assert f"{record.name} is unreadable" in report.stderr


def test_a_damaged_cached_figure_is_set_aside_and_drawn_again(numproject, tmp_path, monkeypatch, capsys):
    (numproject / "figs.yaml").write_text("version: 1\nstages:\n  pic:\n    uses: numstages.basic:Pictured\n")
    msflow.run(numproject / "figs.yaml")
    report = ("report", "-f", "figs.yaml", "-o", tmp_path / "a.html", "-j", "1")
    assert cli(numproject, monkeypatch, capsys, *report)[0] == 0
    run = msflow.run(numproject / "figs.yaml")
    figure = next(k for k in run.session.store.keys() if k != run.key("pic"))  # the one other artifact
    chunks = [p for p in (numproject / ".msflow" / "artifacts").rglob(f"{figure}/**/c/*") if p.is_file()]
    damaged = bytearray(chunks[0].read_bytes())
    damaged[len(damaged) // 2] ^= 0xFF
    chunks[0].write_bytes(bytes(damaged))
    code, _, err = cli(numproject, monkeypatch, capsys, *report)
    assert code == 0 and "1 rendered" in err, err  # drawn again, not an error and not the damaged bytes
    assert [p.name for p in (numproject / ".msflow" / "corrupt").iterdir() if p.name.startswith(figure)]
    assert "data:image/png;base64," in (tmp_path / "a.html").read_text()
    assert cli(numproject, monkeypatch, capsys, "verify", "figs.yaml")[0] == 0
