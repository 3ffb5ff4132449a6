"""Every error a user can cause: exit 2, a message naming file, stage and field, no traceback, nothing written."""

import textwrap

import pytest
import yaml
from conftest import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msflow.cli import main
from msflow.errors import UserError
from msflow.plan import resolve
from msflow.spec import load_pipeline

GOOD_STAGES = """
  src:
    uses: numstages.basic:Source
  scaled:
    uses: numstages.scaling:Scale
    inputs: {x: src.x}
"""

CSV_STAGE = """
  csv:
    uses: numstages.basic:LoadCsv
    inputs: {table: {path: data/table.csv}}
"""

CASES = {
    "invalid_yaml": ("version: 1\nstages: [\n", [], ["invalid YAML", "line"]),
    "unknown_top_level_key": (
        "version: 1\nstagez: {}\nstages:" + GOOD_STAGES,
        [],
        ["unknown key 'stagez'", "field 'stagez'"],
    ),
    "unknown_stage_class": (
        "version: 1\nstages:\n  src:\n    uses: numstages.basic:Sauce\n",
        [],
        ["stage 'src'", "field 'uses'", "no class 'Sauce'", "did you mean 'Source'"],
    ),
    "unknown_stage_module": (
        "version: 1\nstages:\n  src:\n    uses: numstages.nothere:Source\n",
        [],
        ["stage 'src'", "field 'uses'", "unknown stage module 'numstages.nothere'"],
    ),
    "not_a_stage": (
        "version: 1\nstages:\n  src:\n    uses: numstages.basic:NotAStage\n",
        [],
        ["stage 'src'", "field 'uses'", "not a msflow Stage"],
    ),
    "malformed_uses": (
        "version: 1\nstages:\n  src:\n    uses: numstages.basic.Source\n",
        [],
        ["stage 'src'", "field 'uses'", "package.module:Class"],
    ),
    "unknown_param": (
        "version: 1\nstages:\n  src:\n    uses: numstages.basic:Source\n    params: {nn: 3}\n",
        [],
        ["stage 'src'", "field 'params.nn'", "unknown parameter 'nn'", "did you mean 'n'"],
    ),
    "wrongly_typed_param": (
        "version: 1\nstages:\n  src:\n    uses: numstages.basic:Source\n    params: {n: many}\n",
        [],
        ["stage 'src'", "field 'params.n'", "integer"],
    ),
    "missing_required_input": (
        "version: 1\nstages:\n  scaled:\n    uses: numstages.scaling:Scale\n",
        [],
        ["stage 'scaled'", "field 'inputs.x'", "missing required input 'x'"],
    ),
    "unknown_input_name": (
        "version: 1\nstages:" + GOOD_STAGES.replace("{x: src.x}", "{x: src.x, y: src.x}"),
        [],
        ["stage 'scaled'", "field 'inputs.y'", "unknown input 'y'"],
    ),
    "ref_to_unknown_stage": (
        "version: 1\nstages:" + GOOD_STAGES.replace("src.x}", "srcc.x}"),
        [],
        ["stage 'scaled'", "field 'inputs.x'", "unknown stage 'srcc'", "did you mean 'src'"],
    ),
    "ref_to_unknown_output": (
        "version: 1\nstages:" + GOOD_STAGES.replace("src.x}", "src.y}"),
        [],
        ["stage 'scaled'", "field 'inputs.x'", "has no output 'y'", "outputs: x"],
    ),
    "artifact_where_array_expected": (
        "version: 1\nstages:" + GOOD_STAGES.replace("src.x}", "src}"),
        [],
        ["stage 'scaled'", "field 'inputs.x'", "expects one array", "src.<output>"],
    ),
    "files_where_array_expected": (
        "version: 1\nstages:" + GOOD_STAGES.replace("src.x}", "{path: data/table.csv}}"),
        [],
        ["stage 'scaled'", "field 'inputs.x'", "expects a stage reference"],
    ),
    "path_written_as_ref": (
        "version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {table: data/table.csv}\n",
        [],
        ["stage 'csv'", "field 'inputs.table'", "{path: data/table.csv}"],
    ),
    "dependency_cycle": (
        "version: 1\nstages:\n  a:\n    uses: numstages.scaling:Scale\n    inputs: {x: b.y}\n"
        "  b:\n    uses: numstages.scaling:Scale\n    inputs: {x: a.y}\n",
        [],
        ["dependency cycle", "a -> b -> a", "field 'inputs'"],
    ),
    "duplicate_stage_name": (
        "version: 1\nstages:\n  src:\n    uses: numstages.basic:Source\n  src:\n    uses: numstages.basic:Source\n",
        [],
        ["invalid YAML", "duplicate key 'src'", "line 5"],
    ),
    "missing_data_file": (
        "version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n"
        "    inputs: {table: {path: data/nothere.csv}}\n",
        [],
        ["stage 'csv'", "field 'inputs.table'", "data file not found: data/nothere.csv"],
    ),
    "nul_character_in_a_path": (
        "version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n"
        '    inputs: {table: {path: "data/a\\0b.csv"}}\n',
        [],
        ["field 'stages.csv.inputs.table.path'", "a NUL character in 'data/a\\x00b.csv'"],
    ),
    "nul_character_in_a_label": (
        "version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n"
        '    inputs: {table: {"fir\\0st": data/table.csv}}\n',
        [],
        ["field 'stages.csv.inputs.table'", "a NUL character in 'fir\\x00st'"],
    ),
    "glob_matching_nothing": (
        "version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {table: {glob: 'data/*.tsv'}}\n",
        [],
        ["stage 'csv'", "field 'inputs.table'", "matches no files"],
    ),
    "missing_labelled_file": (
        "version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n"
        "    inputs: {table: {first: data/table.csv, second: data/gone.csv}}\n",
        [],
        ["stage 'csv'", "field 'inputs.table.second'", "data/gone.csv"],
    ),
    "unknown_var": (
        "version: 1\nvars: {n: 3}\nstages:\n  src:\n    uses: numstages.basic:Source\n    params: {n: '${m}'}\n",
        [],
        ["field 'stages.src.params.n'", "unknown variable '${m}'"],
    ),
    "var_uses_a_later_var": (
        "version: 1\nvars: {a: '${b}', b: 3}\nstages:" + GOOD_STAGES,
        [],
        ["field 'vars.a'", "unknown variable '${b}'", "the ones declared before it"],
    ),
    "var_unknown_filter": (
        "version: 1\nvars: {a: x.csv, b: '${a:suffix}'}\nstages:" + GOOD_STAGES,
        [],
        ["field 'vars.b'", "'${a:suffix}'", "['name', 'stem']"],
    ),
    "bad_override_syntax": (
        "version: 1\nstages:" + GOOD_STAGES,
        ["-S", "src.n"],
        ["field '-S'", "bad override 'src.n'", "stage.param=value"],
    ),
    "override_without_param": ("version: 1\nstages:" + GOOD_STAGES, ["-S", "src=3"], ["field '-S'", "stage.param"]),
    "override_unknown_stage": (
        "version: 1\nstages:" + GOOD_STAGES,
        ["-S", "srx.n=3"],
        ["field '-S'", "unknown stage 'srx'", "did you mean 'src'"],
    ),
    "override_unknown_param": (
        "version: 1\nstages:" + GOOD_STAGES,
        ["-S", "src.m=3"],
        ["stage 'src'", "field 'params.m'", "unknown parameter 'm'"],
    ),
    "override_unknown_var": (  # a typo must not run the pipeline with the default silently
        "version: 1\nvars: {take: a.mp4, name: a}\nstages:" + GOOD_STAGES,
        ["-S", "vars.tkae=b.mp4"],
        ["field '-S'", "unknown variable 'tkae'", "did you mean 'take'", "['name', 'take']"],
    ),
    "override_empty_var": (  # `-S vars.take="$clip"` with $clip unset
        "version: 1\nvars: {take: a.mp4, name: a}\nstages:" + GOOD_STAGES,
        ["-S", "vars.take="],
        ["field '-S'", "no value for variable 'take'", "unset shell variable", "'a.mp4'"],
    ),
    "publish_a_hidden_file": (  # out/${name}.csv with name empty in the file
        "version: 1\nvars: {name: ''}\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: out/${name}.csv\n",
        [],
        ["field 'publish.scaled.y'", "'out/.csv' names a hidden file", "variable in it empty"],
    ),
    "publish_a_folder": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: out/\n",
        [],
        ["field 'publish.scaled.y'", "'out/' is a folder"],
    ),
    "var_keys_that_become_one": (
        "version: 1\nvars: {a: x}\nstages:\n  src:\n    uses: numstages.basic:Source\n"
        "    params: {n: {'${a}': 1, x: 2}}\n",
        [],
        ["field 'stages.src.params.n'", "two keys become 'x' once the variables are filled in"],
    ),
    "override_wrong_type": (
        "version: 1\nstages:" + GOOD_STAGES,
        ["-S", "src.n=[1,2]"],
        ["stage 'src'", "field 'params.n'"],
    ),
    "nan_param_override": (  # NaN cannot enter a key (strict JSON): it was a traceback from the params memo
        "version: 1\nstages:" + GOOD_STAGES,
        ["-S", "src.offset=.nan"],
        ["stage 'src'", "field 'params'", "params.offset: nan is not allowed"],
    ),
    "unsupported_version": ("version: 7\nstages:" + GOOD_STAGES, [], ["field 'version'", "format version 7"]),
    "top_level_not_mapping": ("- a\n- b\n", [], ["top level must be a mapping"]),
    "empty_file": ("", [], ["empty"]),
    "stage_not_mapping": ("version: 1\nstages:\n  src: numstages.basic:Source\n", [], ["stage 'src'"]),
    "uses_a_standard_library_function": (
        "version: 1\nstages:\n  src:\n    uses: os:getcwd\n",
        [],
        ["stage 'src'", "field 'uses'", "'os:getcwd' is not a msflow Stage subclass", "standard library"],
    ),
    "stage_named_like_a_type_tag": (
        "version: 1\nstages:\n  time:\n    uses: [1]\n",
        [],
        ["bad.yaml: stage 'time': field 'uses': Input should be a valid string"],
    ),
    "union_param_wrong_type": (
        "version: 1\nstages:\n  t:\n    uses: numstages.basic:Tagged\n    params: {k: many}\n",
        [],
        ["stage 't'", "field 'params.k'", "valid integer"],
    ),
    "publish_outside_the_project": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: ../../../tmp/x.npy\n",
        [],
        ["field 'publish.scaled.y'", "is outside the project folder", "--publish-dir"],
    ),
    "publish_to_an_absolute_path": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: /etc/x.npy\n",
        [],
        ["field 'publish.scaled.y'", "'/etc/x.npy' is outside the project folder"],
    ),
    "publish_onto_a_folder": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: data\n",
        [],
        ["field 'publish.scaled.y'", "'data' is a folder"],
    ),
    # publishing runs after the stages: onto a file the run reads, it would replace it without a word
    "publish_onto_an_input": (
        "version: 1\nstages:" + GOOD_STAGES + CSV_STAGE + "publish:\n  csv.x: data/table.csv\n",
        [],
        ["field 'publish.csv.x'", "would overwrite data/table.csv, an input of stage 'csv' (inputs.table)"],
    ),
    "publish_onto_a_globbed_input": (
        "version: 1\nstages:"
        + GOOD_STAGES
        + CSV_STAGE.replace("{path: data/table.csv}", "{glob: 'data/*/*.txt'}")
        + "publish:\n  csv.x: data/parts/b.txt\n",
        [],
        ["field 'publish.csv.x'", "would overwrite data/parts/b.txt, an input of stage 'csv' (inputs.table)"],
    ),
    "publish_into_a_folder_input": (
        "version: 1\nstages:"
        + GOOD_STAGES
        + CSV_STAGE.replace("data/table.csv", "data/parts")
        + "publish:\n  csv.x: data/parts/new.csv\n",
        [],
        ["field 'publish.csv.x'", "would write into data/parts, an input of stage 'csv' (inputs.table)"],
    ),
    "publish_onto_an_input_named_by_variables": (
        "version: 1\nvars: {take: data/table.csv, name: result}\nstages:"
        + GOOD_STAGES
        + CSV_STAGE.replace("data/table.csv", "'${take}'")
        + "publish:\n  csv.x: data/${name}.csv\n",
        ["-S", "vars.name=table"],
        ["field 'publish.csv.x'", "'data/table.csv' would overwrite data/table.csv, an input of stage 'csv'"],
    ),
    "publish_onto_the_pipeline_file": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: ./bad.yaml\n",
        [],
        ["field 'publish.scaled.y'", "would overwrite bad.yaml, the pipeline file itself"],
    ),
    "publish_onto_another_pipeline_file": (  # p_self.yaml publishing its BVH onto pipeline.yaml
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: pipeline.yaml\n",
        [],
        ["field 'publish.scaled.y'", "would overwrite pipeline.yaml, another pipeline file"],
    ),
    "publish_onto_the_lock": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: bad.lock\n",
        [],
        ["field 'publish.scaled.y'", "would overwrite bad.lock, the pipeline's lock file"],
    ),
    "publish_into_the_store": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: .msflow/runs/x.json\n",
        [],
        ["field 'publish.scaled.y'", "would write into .msflow, msflow's store"],
    ),
    "publish_one_file_twice": (
        "version: 1\nstages:" + GOOD_STAGES + "publish:\n  scaled.y: out/a.npy\n  src.x: out/./a.npy\n",
        [],
        ["field 'publish.src.x'", "also published by 'scaled.y'"],
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_user_error_exit_2_named_location_no_traceback_nothing_written(numproject, case):
    text, extra, expected = CASES[case]
    (numproject / "bad.yaml").write_text(text)
    result = run_cli(numproject, "run", "bad.yaml", *extra)
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    assert "bad.yaml" in result.stderr
    for fragment in expected:
        assert fragment in result.stderr, (fragment, result.stderr)
    assert "params.k.int" not in result.stderr  # pydantic's type tags are no field names
    assert not (numproject / ".msflow").exists()  # nothing written
    assert not (numproject / "bad.lock").exists()


def test_missing_pipeline_file(numproject):
    result = run_cli(numproject, "run", "nothere.yaml")
    assert result.returncode == 2 and "nothere.yaml: pipeline file not found" in result.stderr
    assert "nearest" not in result.stderr


@pytest.mark.parametrize("command", ["run", "status"])
def test_a_command_typed_in_a_subfolder_names_the_pipeline_above(numproject, command):
    (numproject / "out").mkdir()
    result = run_cli(numproject / "out", command)
    assert result.returncode == 2 and "pipeline.yaml: pipeline file not found" in result.stderr, result.stderr
    assert "the nearest is ../pipeline.yaml (give it as the FILE argument)" in result.stderr, result.stderr


@pytest.mark.parametrize(
    "table, expected",
    [
        ("{path: data/table.csv}", "data file not found: data/table.csv (paths are relative to the pipeline file's "
         "folder, sub; from there it is '../data/table.csv')"),
        ("{glob: 'data/*.csv'}", "the glob 'data/*.csv' matches no files (paths are relative to the pipeline file's "
         "folder, sub; from there it is '../data/*.csv')"),
        ("{path: data/gone.csv}", "data file not found: data/gone.csv (paths are relative to the pipeline file's "
         "folder, sub)"),
    ],
)  # fmt: skip
def test_a_path_written_from_the_working_directory_gets_the_path_to_write(numproject, table, expected):
    """Paths in a pipeline start at its file's folder. A path that names a file only from the working directory
    (``-S vars.take=clip.mp4`` for a pipeline in a subfolder) is the usual slip: the error says where paths start
    and what to write instead."""
    (numproject / "sub").mkdir()
    (numproject / "sub" / "p.yaml").write_text(
        f"version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {{table: {table}}}\n"
    )
    result = run_cli(numproject, "run", "sub/p.yaml")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert expected in result.stderr, result.stderr
    assert not list(numproject.rglob(".msflow"))  # nothing written


def test_a_path_far_from_the_pipeline_is_suggested_absolute(numproject):
    """From a pipeline two folders down, the file the user named is '../../data/table.csv': the hint gives its
    absolute path instead of a climb of '..' (one '..' up is still shown relative, as above)."""
    (numproject / "sub" / "deep").mkdir(parents=True)
    (numproject / "sub" / "deep" / "p.yaml").write_text(
        "version: 1\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {table: {path: data/table.csv}}\n"
    )
    result = run_cli(numproject, "run", "sub/deep/p.yaml")
    assert result.returncode == 2 and "../.." not in result.stderr, result.stderr
    assert f"from there it is '{(numproject / 'data' / 'table.csv').resolve()}'" in result.stderr, result.stderr


def test_a_leading_tilde_in_a_data_path_is_the_home_folder(numproject):
    """``-S vars.x=~/file``: no shell expands '~' after '=', so msflow does (a folder named '~' is no one's intent);
    a missing file's error shows the path it looked at."""
    (numproject / "p.yaml").write_text(
        "version: 1\nvars: {table: data/table.csv}\nstages:\n  csv:\n    uses: numstages.basic:LoadCsv\n"
        "    inputs: {table: {path: '${table}'}}\n"
    )
    home = {"HOME": str(numproject / "data")}
    assert run_cli(numproject, "run", "p.yaml", "-S", "vars.table=~/table.csv", env=home).returncode == 0
    result = run_cli(numproject, "run", "p.yaml", "-S", "vars.table=~/gone.csv", env=home)
    assert result.returncode == 2 and f"data file not found: {numproject / 'data' / 'gone.csv'}" in result.stderr


def test_stage_user_error_exits_2_and_keeps_earlier_results(numproject):
    assert run_cli(numproject, "run", "-q").returncode == 0
    before = sorted(p.name for p in (numproject / ".msflow" / "artifacts").glob("*/*"))
    (numproject / "data" / "table.csv").write_text("1,2,x\n")
    result = run_cli(numproject, "run", "-q")
    assert result.returncode == 2
    assert "stage 'csv'" in result.stderr and "field 'inputs.table'" in result.stderr
    assert "table.csv" in result.stderr and "Traceback" not in result.stderr
    after = sorted(p.name for p in (numproject / ".msflow" / "artifacts").glob("*/*"))
    assert set(before) <= set(after)  # earlier artifacts intact
    (numproject / "data" / "table.csv").write_text("1,2,3\n4,5,6\n")
    again = run_cli(numproject, "run", "-q")
    assert again.returncode == 0


@pytest.mark.parametrize(
    "mode, code, fragments",
    [
        ("schema", 1, ["stage 'broken'", "output 'y'", "axis 0 has size 4, expected 3"]),
        ("nan_meta", 1, ["stage 'broken' meta.bad", "nan", "not allowed in strict JSON"]),
        ("crash", 1, ["stage 'broken' failed: RuntimeError: boom", "Traceback"]),
        ("user", 2, ["error: broken.yaml: stage 'broken': field 'inputs.x': the data is unusable"]),
    ],
)
def test_failing_stage_reports_stage_and_output(numproject, mode, code, fragments):
    (numproject / "broken.yaml").write_text(
        textwrap.dedent(f"""
        version: 1
        stages:
          ok:
            uses: numstages.basic:Source
          broken:
            uses: numstages.basic:Broken
            params: {{mode: {mode}}}
    """)
    )
    result = run_cli(numproject, "run", "broken.yaml")
    assert result.returncode == code, result.stderr
    for fragment in fragments:
        assert fragment in result.stderr, (fragment, result.stderr)
    if code == 2:
        assert "Traceback" not in result.stderr
    import msflow

    rerun = msflow.run(numproject / "broken.yaml", until="ok")
    assert rerun.executed == []  # the healthy stage's result survived the failure


# ------------------------------------------------------------------------------------------------ fuzzing
KEYS = [
    "version",
    "store",
    "vars",
    "stages",
    "publish",
    "uses",
    "inputs",
    "params",
    "src",
    "scaled",
    "x",
    "n",
    "path",
    "glob",
    "description",
    "numstages.basic:Source",
    "src.x",
    "${n}",
    "${x}",
    "data/table.csv",
    "data/\x00.csv",  # a path the operating system refuses with a ValueError, not an OSError
]
scalars = (
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=12) | st.sampled_from(KEYS)
)
structures = st.recursive(
    scalars,
    lambda children: (
        st.lists(children, max_size=4)
        | st.dictionaries(st.sampled_from(KEYS) | st.text(max_size=6), children, max_size=5)
    ),
    max_leaves=25,
)


def _load_and_resolve(path, overrides=()):
    pipeline = load_pipeline(path, overrides)
    resolve(pipeline, {})


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=structures)
def test_fuzz_structured_documents_never_raise_anything_but_user_error(numproject, doc):
    path = numproject / "fuzz.yaml"
    path.write_text(yaml.safe_dump(doc))
    try:
        _load_and_resolve(path)
    except UserError as exc:
        assert str(exc)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    text=st.text(alphabet=st.sampled_from(list("ab:-[]{}\n '\"&*!|>%@`#,?${}.1")), max_size=80),
    overrides=st.lists(st.text(max_size=10), max_size=2),
)
def test_fuzz_raw_text_and_overrides_never_raise_anything_but_user_error(numproject, text, overrides):
    path = numproject / "fuzz.yaml"
    path.write_text("version: 1\nstages:" + GOOD_STAGES + text)
    try:
        _load_and_resolve(path, tuple(overrides))
    except UserError as exc:
        assert str(exc)


def test_cli_main_in_process_returns_2_for_user_errors(numproject, capsys, monkeypatch):
    monkeypatch.chdir(numproject)
    (numproject / "bad.yaml").write_text("version: 1\nstages: {}\n")
    assert main(["run", "bad.yaml"]) == 2
    assert "'stages' is empty" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["frobnicate"], "No such command 'frobnicate'"),
        (["run", "--jobs", "x"], "Invalid value for '-j'"),
        (["show", "--nope", "src"], "No such option: --nope"),
        (["run", "-j", "0"], "-j must be at least 1"),
        (["run", "--until", "nope"], "field '--until': unknown stage 'nope'"),
        (["run", "--force", "nope"], "field '--force': unknown stage(s) ['nope']"),
    ],
)
def test_cli_usage_errors_exit_2_without_traceback(numproject, args, fragment):
    result = run_cli(numproject, *args)
    assert result.returncode == 2, result.stderr
    assert fragment in result.stderr and "Traceback" not in result.stderr


# ------------------------------------------------------------------------------------------------ publishing, corruption
def test_publishing_onto_a_folder_made_after_loading_is_a_user_error_leaving_no_temporary_file(numproject):
    text = (numproject / "pipeline.yaml").read_text()
    (numproject / "pipeline.yaml").write_text(text + "publish:\n  scaled.y: out/scaled.npy\n")
    from msflow.session import open_session

    session = open_session(numproject / "pipeline.yaml")  # loaded while out/scaled.npy is not a folder
    (numproject / "out" / "scaled.npy").mkdir(parents=True)
    import msflow

    with pytest.raises(UserError, match=r"out/scaled.npy: is a folder") as err:
        msflow.run(numproject / "pipeline.yaml", session=session)
    assert err.value.field == "publish.scaled.y"
    leftovers = [p.name for p in numproject.rglob("*.tmp")]
    assert leftovers == [] and list((numproject / "out" / "scaled.npy").iterdir()) == []


@pytest.mark.parametrize("command", ["show", "export"])
def test_show_and_export_of_a_corrupt_artifact_exit_1_naming_it(numproject, tmp_path, command):
    assert run_cli(numproject, "run", "-q").returncode == 0
    lock = yaml.safe_load((numproject / "pipeline.lock").read_text())
    key = lock["stages"]["scaled"]["key"]
    manifest = numproject / ".msflow" / "artifacts" / key[:2] / key / "zarr.json"
    manifest.write_bytes(manifest.read_bytes()[:100])
    args = ["show", "scaled"] if command == "show" else ["export", "scaled.y", tmp_path / "y.csv"]
    result = run_cli(numproject, *args)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert f"the artifact {key} of stage 'scaled' is corrupt" in result.stderr and "msflow verify" in result.stderr


def test_error_messages_name_files_relative_to_the_current_folder(numproject):
    result = run_cli(numproject, "run", str(numproject / "pipeline.yaml"), "-S", "src.n=many")
    assert result.returncode == 2
    assert result.stderr.startswith("error: pipeline.yaml: stage 'src': field 'params.n'"), result.stderr
