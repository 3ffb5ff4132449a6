"""``publish:`` after a run: never onto what the run reads, a warning when one pipeline replaces a file another
published, and the list of the files published (full path and no-op fast path alike)."""

import json

from conftest import run_cli


def add_publish(path, entries, text=None):
    """Write ``path`` as the numeric pipeline (or ``text``) with these ``publish:`` entries."""
    base = text if text is not None else path.read_text()
    path.write_text(base + "publish:\n" + "".join(f"  {ref}: {dest}\n" for ref, dest in entries.items()))


def newest_record(proj):
    return json.loads(sorted((proj / ".msflow" / "runs").glob("*.json"))[-1].read_text())


def test_a_clip_given_on_the_command_line_is_never_overwritten_by_a_publish_entry(numproject):
    """``-S vars.take=../out/clip_preview.mp4 -S vars.name=clip`` with the preview published to
    out/${name}_preview.mp4: the run stops at load, before any stage, and the user's file stays as it was."""
    (numproject / "pyproject.toml").write_text("")  # the project's root, above the pipeline's folder
    sub = numproject / "pipelines"
    sub.mkdir()
    (numproject / "out").mkdir()
    clip = numproject / "out" / "clip_preview.csv"
    clip.write_text((numproject / "data" / "table.csv").read_text())
    before = clip.read_bytes()
    add_publish(
        sub / "capture.yaml",
        {"csv.x": "../out/${name}_preview.csv"},
        "version: 1\nstore: ../.msflow\nvars: {take: ../data/table.csv, name: table}\nstages:\n"
        "  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {table: {path: '${take}'}}\n",
    )
    result = run_cli(numproject, "run", "pipelines/capture.yaml", "-S", "vars.take=../out/clip_preview.csv",
                     "-S", "vars.name=clip")  # fmt: skip
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    expected = (
        "pipelines/capture.yaml: field 'publish.csv.x': '../out/clip_preview.csv' would overwrite "
        "out/clip_preview.csv, an input of stage 'csv' (inputs.table)"
    )
    assert expected in result.stderr, result.stderr
    assert clip.read_bytes() == before
    assert not (numproject / ".msflow" / "runs").exists()  # no stage ran


def test_another_pipelines_lock_is_never_overwritten_by_a_publish_entry(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    lock = (numproject / "pipeline.lock").read_bytes()
    add_publish(numproject / "other.yaml", {"scaled.y": "pipeline.lock"}, (numproject / "pipeline.yaml").read_text())
    result = run_cli(numproject, "run", "-q", "other.yaml")
    expected = "other.yaml: field 'publish.scaled.y': 'pipeline.lock' would overwrite pipeline.lock, another pipeline's"
    assert result.returncode == 2 and expected in result.stderr, result.stderr
    assert (numproject / "pipeline.lock").read_bytes() == lock
    (numproject / "notes.lock").write_text("not msflow's\n")  # any other .lock file is the user's to publish onto
    add_publish(numproject / "other.yaml", {"scaled.y": "notes.lock"}, (numproject / "pipeline.yaml").read_text())
    assert "unsupported export format '.lock'" in run_cli(numproject, "run", "-q", "other.yaml").stderr


def test_replacing_a_file_another_pipeline_published_is_a_warning_a_new_result_of_the_same_is_not(numproject):
    pipeline = numproject / "pipeline.yaml"
    text = pipeline.read_text()
    add_publish(pipeline, {"scaled.y": "out/y.csv"})
    add_publish(numproject / "other.yaml", {"scaled.y": "out/y.csv"}, text.replace("factor: 3", "factor: 5"))
    first = run_cli(numproject, "run", "-q")
    assert first.returncode == 0 and "warning" not in first.stderr, first.stderr

    replaced = run_cli(numproject, "run", "-q", "other.yaml")
    assert replaced.returncode == 0, replaced.stderr
    warning = "warning: out/y.csv was published by pipeline.yaml (scaled.y); replaced by other.yaml (scaled.y)"
    assert warning in replaced.stderr, replaced.stderr
    back = run_cli(numproject, "run", "-q")  # the next plain run puts its own back: said too
    warning = "warning: out/y.csv was published by other.yaml (scaled.y); replaced by pipeline.yaml (scaled.y)"
    assert back.returncode == 0 and warning in back.stderr, back.stderr
    assert (numproject / "out" / "y.csv").read_text().splitlines()[2] == "3"

    changed = run_cli(numproject, "run", "-q", "-S", "scaled.factor=7")  # a new result of the same entry
    assert changed.returncode == 0 and "warning" not in changed.stderr, changed.stderr
    assert (numproject / "out" / "y.csv").read_text().splitlines()[2] == "7"

    ledger = json.loads((numproject / ".msflow" / "cache" / "published.json").read_text())
    assert ledger == {"out/y.csv": {"pipeline": "pipeline.yaml", "entry": "scaled.y"}}


def test_replacing_a_file_with_another_entry_of_the_same_pipeline_is_a_warning(numproject):
    pipeline = numproject / "pipeline.yaml"
    text = pipeline.read_text().replace("  n: 6\n", "  n: 6\n  what: y\n")
    add_publish(pipeline, {"scaled.y": "out/${what}.npy", "src.x": "out/x.npy"}, text)
    assert run_cli(numproject, "run", "-q").returncode == 0
    result = run_cli(numproject, "run", "-q", "-S", "vars.what=x", "-S", "src.n=3")
    # scaled.y now goes to out/x.npy, which src.x published; src.x goes there too: refused at load
    assert result.returncode == 2 and "also published by" in result.stderr, result.stderr
    add_publish(pipeline, {"scaled.y": "out/${what}.npy"}, text)
    result = run_cli(numproject, "run", "-q", "-S", "vars.what=x")
    warning = "warning: out/x.npy was published by pipeline.yaml (src.x); replaced by pipeline.yaml (scaled.y)"
    assert result.returncode == 0 and warning in result.stderr, result.stderr


def test_a_run_lists_the_files_it_wrote_as_published_and_the_others_as_up_to_date(numproject):
    """``published:`` names only the files the run wrote; a file that held the same output already is listed as
    up to date, all of them after a no-op (fast path and full path alike)."""
    add_publish(numproject / "pipeline.yaml", {"scaled.y": "out/y.csv", "src.x": "out/x.npy"})
    first = run_cli(numproject, "run", "-q")
    assert first.returncode == 0, first.stderr
    assert first.stdout.splitlines() == ["published: out/y.csv, out/x.npy"]
    stamps = {p.name: p.stat().st_mtime_ns for p in (numproject / "out").iterdir()}

    noop = run_cli(numproject, "run", "-q")
    assert noop.returncode == 0 and noop.stdout.splitlines() == ["published files up to date: out/y.csv, out/x.npy"]
    assert newest_record(numproject)["executor"] == "none"  # answered by the fast path, from the saved state
    full = run_cli(numproject, "run", "-q", env={"MSFLOW_FASTPATH": "0"})  # the full path says the same
    assert full.stdout == noop.stdout, full.stdout
    elsewhere = run_cli(numproject / "out", "run", "../pipeline.yaml")  # paths relative to the working folder
    assert elsewhere.stdout.splitlines() == ["published files up to date: y.csv, x.npy"], elsewhere.stdout
    assert {p.name: p.stat().st_mtime_ns for p in (numproject / "out").iterdir()} == stamps  # none was written

    (numproject / "out" / "y.csv").unlink()
    again = run_cli(numproject, "run", "-q", env={"MSFLOW_FASTPATH": "0"})  # the full path: republished, listed
    assert again.stdout.splitlines() == ["published: out/y.csv", "published files up to date: out/x.npy"]
    assert (numproject / "out" / "y.csv").exists()
    assert (numproject / "out" / "x.npy").stat().st_mtime_ns == stamps["x.npy"]


def test_an_override_that_drops_a_variable_the_published_names_use_is_a_warning_before_the_run(numproject):
    """``out/y_${name}.csv`` with ``name: times_${factor}`` and ``scaled.factor: ${factor}``: ``-S scaled.factor=5``
    writes five times x into a file named for three, so the run says so before any stage runs (and a no-op repeat
    too), naming the override, the variables, the files and the variable that renames them."""
    pipeline = numproject / "pipeline.yaml"
    text = pipeline.read_text().replace("  n: 6\n", "  n: 6\n  factor: 3\n  name: times_${factor}\n")
    add_publish(pipeline, {"scaled.y": "out/y_${name}.csv"}, text.replace("factor: 3}", "factor: '${factor}'}"))
    warning = (
        "warning: -S scaled.factor no longer uses ${factor}, which the published files are named after (through "
        "${name}): out/y_times_3.csv will hold the override's result under names that no longer say what it is; "
        "name them for it with -S vars.name=..."
    )
    for attempt in ("first", "no-op"):
        result = run_cli(numproject, "run", "-S", "scaled.factor=5")
        assert result.returncode == 0 and warning in result.stderr, (attempt, result.stderr)
        lines = result.stderr.splitlines()
        assert lines.index(warning) < min(i for i, line in enumerate(lines) if " scaled " in line), lines
    assert newest_record(numproject)["executor"] == "none"  # the no-op came from the fast path's saved state
    assert (numproject / "out" / "y_times_3.csv").read_text().splitlines()[2] == "5"

    for kept in (["-S", "scaled.factor=${factor}"], ["-S", "scaled.factor=5", "-S", "vars.name=times_5"]):
        result = run_cli(numproject, "run", "-q", *kept)  # the variable kept, or the files renamed: nothing to say
        assert result.returncode == 0 and "warning" not in result.stderr, (kept, result.stderr)


def named_after_a_variable(numproject):
    """The numeric pipeline with ``scaled.factor: ${factor}`` and ``scaled.y`` published to out/y_${name}.csv,
    ``name`` being ``times_${factor}``; returns its path."""
    pipeline = numproject / "pipeline.yaml"
    text = pipeline.read_text().replace("  n: 6\n", "  n: 6\n  factor: 3\n  name: times_${factor}\n")
    add_publish(pipeline, {"scaled.y": "out/y_${name}.csv"}, text.replace("factor: 3}", "factor: '${factor}'}"))
    return pipeline


def test_the_warning_goes_by_what_the_overrides_leave_and_the_variables_they_set(numproject):
    """The value the overrides leave in the param decides, not each -S alone: a later -S that puts the variable back
    says nothing, one that replaces it again says it once. A variable the command line sets (-S vars.factor=5)
    renames the files itself: nothing to say about it (docs/framework.md, "a -S vars.... that renames the files,
    says nothing")."""
    from msflow.spec import load_pipeline

    pipeline = named_after_a_variable(numproject)
    assert len(load_pipeline(pipeline, ["scaled.factor=5"]).warnings) == 1
    assert load_pipeline(pipeline, ["scaled.factor=5", "scaled.factor=${factor}"]).warnings == ()
    assert len(load_pipeline(pipeline, ["scaled.factor=5", "scaled.factor=6"]).warnings) == 1
    assert load_pipeline(pipeline, ["scaled.factor=5", "vars.factor=5"]).warnings == ()
    assert load_pipeline(pipeline, ["vars.factor=5", "scaled.factor=5"]).warnings == ()
