"""Takes as data: labelled files from a glob with fields parsed from file names, or written per file; the fields
reach the stage (Files.fields) and its cache key; every mistake is a clear user error."""

import json

import pytest
from conftest import run_cli

import msflow
from msflow.spec import compile_label_pattern


def _write(project, body):
    (project / "clips").mkdir(exist_ok=True)
    for name in ("1001_DFA_ANG_XX.flv", "1001_DFA_HAP_XX.flv", "1002_IEO_SAD_HI.flv"):
        (project / "clips" / name).write_bytes(name.encode())
    (project / "takes.yaml").write_text(
        f"version: 1\nstages:\n  takes:\n    uses: numstages.basic:Takes\n    inputs:\n      takes: {body}\n"
    )
    return project / "takes.yaml"


def _meta(project, *overrides):
    result = msflow.run(project / "takes.yaml", overrides=list(overrides))
    return result.artifact("takes").meta


@pytest.mark.parametrize(
    "pattern, name, expected",
    [
        (
            "{speaker}_{sentence}_{expression}_{level}",
            "1001_DFA_ANG_XX",
            {"speaker": "1001", "sentence": "DFA", "expression": "ANG", "level": "XX"},
        ),
        ("{speaker}_*_{expression}_*", "1001_DFA_ANG_XX", {"speaker": "1001", "expression": "ANG"}),
        ("take-{n}", "take-12", {"n": "12"}),
        ("{a}.{b}*", "x.y.z", {"a": "x", "b": "y"}),
        ("clip {n}", "clip 7", {"n": "7"}),
    ],
)
def test_label_pattern_reads_fields(pattern, name, expected):
    m = compile_label_pattern(pattern).fullmatch(name)
    assert m is not None and m.groupdict() == expected


def test_label_pattern_rejects_other_names():
    assert compile_label_pattern("{speaker}_{expression}").fullmatch("nounderscore") is None
    assert compile_label_pattern("s{id}.wav").fullmatch("t1.wav") is None
    assert compile_label_pattern("{speaker}_{expression}").fullmatch("1001_DFA_ANG") is None  # no separators


def test_glob_with_pattern_gives_labels_and_fields(numproject):
    _write(
        numproject,
        '{glob: "clips/*.flv", pattern: "{speaker}_{sentence}_{expression}_{level}", label: "{speaker}-{expression}"}',
    )
    meta = _meta(numproject)
    assert meta["labels"] == ["1001-ANG", "1001-HAP", "1002-SAD"]
    assert meta["fields"]["1002-SAD"] == {"speaker": "1002", "sentence": "IEO", "expression": "SAD", "level": "HI"}


def test_default_label_is_the_file_stem(numproject):
    _write(numproject, '{glob: "clips/*.flv", pattern: "{speaker}_*"}')
    meta = _meta(numproject)
    assert meta["labels"] == ["1001_DFA_ANG_XX", "1001_DFA_HAP_XX", "1002_IEO_SAD_HI"]
    assert meta["fields"]["1002_IEO_SAD_HI"] == {"speaker": "1002"}


@pytest.mark.parametrize(
    "where, body, labels",
    [
        ("clips", "{path: clips/1001_DFA_ANG_XX.flv}", ["1001_DFA_ANG_XX.flv"]),
        ("clips", '{glob: "clips/*.flv"}', ["1001_DFA_ANG_XX.flv", "1001_DFA_HAP_XX.flv", "1002_IEO_SAD_HI.flv"]),
        (
            "clips/a",
            '{glob: "clips/*/*.flv"}',
            ["a/1001_DFA_ANG_XX.flv", "a/1001_DFA_HAP_XX.flv", "a/1002_IEO_SAD_HI.flv"],
        ),
    ],
)
def test_a_file_written_another_way_or_moved_keeps_its_key(numproject, tmp_path, where, body, labels):
    """The label of ``{path: file}`` is the file's name and a glob's are the paths below its folder, so the key,
    which holds the labels, holds no folder: the same files written as an absolute path, or moved elsewhere with
    their folder, are the cached result (a capture's clip referenced differently must not be tracked again)."""
    clips = numproject / "clips"
    _write(numproject, body)
    if where != "clips":  # the files one folder further down, for the glob over folders
        (clips / "a").mkdir()
        for f in clips.glob("*.flv"):
            f.rename(clips / "a" / f.name)
    first = msflow.run(numproject / "takes.yaml")
    assert first.artifact("takes").meta["labels"] == labels
    elsewhere = tmp_path / "somewhere else" / "clips"
    elsewhere.parent.mkdir()
    clips.rename(elsewhere)
    moved = body.replace("clips/", f"{elsewhere.as_posix()}/")
    (numproject / "takes.yaml").write_text((numproject / "takes.yaml").read_text().replace(body, moved))
    again = msflow.run(numproject / "takes.yaml")
    assert again.executed == [] and again.key("takes") == first.key("takes")


def test_fields_written_per_file_and_in_the_key(numproject):
    body = "{a: {path: clips/1001_DFA_ANG_XX.flv, speaker: 1001, expression: angry}, b: clips/1001_DFA_HAP_XX.flv}"
    _write(numproject, body)
    meta = _meta(numproject)
    assert meta["fields"] == {"a": {"speaker": "1001", "expression": "angry"}, "b": {}}
    (numproject / "takes.yaml").write_text((numproject / "takes.yaml").read_text().replace("angry", "happy"))
    why = run_cli(numproject, "why", "takes", "-f", "takes.yaml")
    assert "input takes: fields of a changed" in why.stdout
    assert _meta(numproject)["fields"]["a"]["expression"] == "happy"


def test_plain_file_inputs_keep_their_keys(numproject):
    """A files input without fields hashes exactly as before fields existed (no needless reruns)."""
    result = msflow.run(numproject / "pipeline.yaml")
    record = json.loads(sorted((numproject / ".msflow" / "runs").glob("*.json"))[-1].read_text())
    assert record["stages"]["csv"]["key_parts"]["inputs"]["table"].keys() == {"files"}
    assert result.ok


@pytest.mark.parametrize(
    "body, message, field",
    [
        (
            '{glob: "clips/*.flv", pattern: "{speaker}_{sentence}_{expression}"}',
            "'1001_DFA_ANG_XX.flv' does not match the label pattern",
            "inputs.takes.pattern",
        ),
        (
            '{glob: "clips/*.flv", pattern: "{speaker}_*", label: "{speaker}"}',
            "label '1001' names two files",
            "inputs.takes.label",
        ),
        (
            '{glob: "clips/*.flv", pattern: "{speaker}_*", label: "{mood}"}',
            "must be a template of the pattern's fields",
            "inputs.takes.label",
        ),
        ('{glob: "clips/*.flv", pattern: "no_fields"}', "has no {field}", "inputs.takes.pattern"),
        ('{glob: "empty/*.flv", pattern: "{speaker}"}', "matches no files", "inputs.takes"),
        ('{glob: "clips/*.flv", label: "{speaker}"}', "needs a 'pattern'", "inputs.takes.label"),
        ("{a: {path: clips/1001_DFA_ANG_XX.flv, speaker: [1, 2]}}", "bad fields: ['speaker']", "inputs.takes.a"),
        ("{a: {speaker: 1001}}", "{path: file, field: value", "inputs.takes.a"),
    ],
)
def test_labelled_file_mistakes_are_user_errors(numproject, body, message, field):
    _write(numproject, body)
    (numproject / "empty").mkdir()
    got = run_cli(numproject, "run", "takes.yaml")
    assert got.returncode == 2, got.stderr
    assert message in got.stderr and "Traceback" not in got.stderr
    assert "takes.yaml" in got.stderr and "takes" in got.stderr and field in got.stderr
    assert not (numproject / ".msflow" / "runs").exists() or not list((numproject / ".msflow" / "runs").glob("*"))


def test_run_stage_accepts_fields():
    from msflow.testing import files_input

    files = files_input({"a": {"path": __file__, "speaker": 7}})
    assert files.field("a", "speaker") == "7" and files["a"].name == "test_core_labelled_files.py"


def test_a_file_name_that_is_not_utf8_is_a_user_error(numproject):
    """Labels, keys and run records are UTF-8 JSON; a file whose name has other bytes is named, escaped, and
    refused (exit 2), whether a glob finds it or an override names it."""
    import os

    _write(numproject, '{glob: "clips/*.flv"}')
    odd = os.path.join(os.fsencode(numproject / "clips"), b"take\xff.flv")
    with open(odd, "wb") as fh:
        fh.write(b"bytes")
    found = run_cli(numproject, "run", "takes.yaml")
    assert found.returncode == 2 and "not a UTF-8 file name" in found.stderr and "take\\udcff.flv" in found.stderr
    assert "Traceback" not in found.stderr
    (numproject / "one.yaml").write_text(
        "version: 1\nvars: {take: clips/1001_DFA_ANG_XX.flv}\nstages:\n  takes:\n    uses: numstages.basic:Takes\n"
        "    inputs:\n      takes: {path: '${take}'}\n"
    )
    named = run_cli(numproject, "run", "one.yaml", "-S", "vars.take=" + os.fsdecode(odd))
    assert named.returncode == 2 and "not UTF-8 text" in named.stderr and "Traceback" not in named.stderr
