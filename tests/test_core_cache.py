"""Incremental runs on the numeric test project: what reruns after which change (msflow core, issue 2)."""

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import executions

import msflow

ALL = ["src", "scaled", "sign", "csv", "total"]


@pytest.fixture
def log(tmp_path, monkeypatch):
    path = tmp_path / "executions.log"
    monkeypatch.setenv("NUMSTAGES_LOG", str(path))
    return path


def run(proj, *overrides, **options):
    return msflow.run(proj / "pipeline.yaml", overrides=overrides, **options)


def expected_total(n=6, factor=3.0, offset=0.0):
    x = np.arange(n, dtype=float) + offset
    return float(np.sign(x * factor).sum() + 21.0)


def test_first_run_computes_everything_and_noop_rerun_runs_nothing(numproject, log):
    first = run(numproject)
    assert sorted(first.executed) == sorted(ALL)
    assert first.load("total.total") == pytest.approx(expected_total())
    second = run(numproject, jobs=2)
    assert second.executed == []
    assert second.record["executor"] == "none"  # everything cached: no process pool was started
    assert all(s.state == "cached" for s in second.states.values())
    assert sorted(executions(log)) == sorted(ALL)  # each stage executed exactly once over both runs
    assert second.key("total") == first.key("total")


def test_param_change_reruns_that_stage_and_its_dependents_only(numproject, log):
    run(numproject)
    log.unlink()
    changed = run(numproject, "src.offset=1")
    assert sorted(changed.executed) == ["scaled", "sign", "src", "total"]  # csv does not depend on src
    assert changed.load("total.total") == pytest.approx(expected_total(offset=1.0))
    assert run(numproject, "src.offset=1").executed == []


def test_early_cutoff_stops_invalidation(numproject, log):
    run(numproject)
    # factor 3 -> 5 changes scaled.y, but sign(y) is unchanged, so total is not rerun
    result = run(numproject, "scaled.factor=5")
    assert sorted(result.executed) == ["scaled", "sign"]
    assert result.states["total"].state == "cached"


def test_comment_docstring_and_formatting_edit_reruns_nothing(numproject, log):
    run(numproject)
    module = numproject / "numstages" / "scaling.py"
    source = module.read_text()
    edited = source.replace(
        '"""Scaling: the only stage module importing numstages.helpers."""',
        '"""A different docstring."""\n# a comment\n',
    )
    edited = edited.replace(
        'return Result({"y": double(inputs["x"]) * params.factor / 2})',
        'return Result( { "y" : double( inputs[ "x" ] )*params.factor/2 } )  # spaced',
    )
    assert edited != source
    module.write_text(edited)
    assert run(numproject).executed == []


def test_edit_to_imported_helper_module_reruns_its_importer(numproject, log):
    run(numproject)
    helper = numproject / "numstages" / "helpers.py"
    helper.write_text(helper.read_text().replace("return 2 * np.asarray(x)", "return np.asarray(x) * 2.0"))
    result = run(numproject)
    # scaling imports helpers; the result is numerically identical, so sign and total stay cached
    assert result.executed == ["scaled"]
    why = result.states["scaled"]
    assert why.state == "ran"


def test_semantic_edit_to_helper_changes_results(numproject, log):
    run(numproject)
    helper = numproject / "numstages" / "helpers.py"
    helper.write_text(helper.read_text().replace("return 2 * np.asarray(x)", "return -2 * np.asarray(x)"))
    result = run(numproject)
    assert sorted(result.executed) == ["scaled", "sign", "total"]
    assert result.load("total.total") == pytest.approx(21.0 - 5.0)


def test_touched_data_file_reruns_nothing_changed_content_reruns(numproject, log):
    run(numproject)
    table = numproject / "data" / "table.csv"
    st = table.stat()
    os.utime(table, ns=(st.st_atime_ns + 10**9, st.st_mtime_ns + 10**9))
    assert run(numproject).executed == []
    table.write_text("1,2,3\n4,5,7\n")
    result = run(numproject)
    assert sorted(result.executed) == ["csv", "total"]
    assert result.load("total.total") == pytest.approx(expected_total() + 1)


def test_cloned_project_directory_reruns_nothing(numproject, tmp_path, log):
    first = run(numproject)
    clone = tmp_path / "elsewhere" / "clone"
    shutil.copytree(numproject, clone)
    second = run(clone)
    assert second.executed == []
    assert {n: second.key(n) for n in ALL} == {n: first.key(n) for n in ALL}


def test_keys_do_not_depend_on_location_or_mtimes(numproject, tmp_path, log):
    """A fresh store in a copy computes everything again, to the same keys and content."""
    first = run(numproject)
    clone = tmp_path / "fresh"
    shutil.copytree(numproject, clone, ignore=shutil.ignore_patterns(".msflow"))
    for path in clone.rglob("*"):
        os.utime(path, ns=(10**18, 10**18))
    second = run(clone)
    assert sorted(second.executed) == sorted(ALL)
    for name in ALL:
        assert second.key(name) == first.key(name)
        assert second.states[name].manifest["content_hash"] == first.states[name].manifest["content_hash"]


def test_force_reruns_stage_even_when_cached(numproject, log):
    run(numproject)
    result = run(numproject, force=["src"])
    assert result.executed[0] == "src"
    assert "total" not in result.executed  # identical content: early cutoff


def test_until_runs_only_the_stage_and_its_ancestors(numproject, log):
    result = run(numproject, until="scaled")
    assert sorted(result.executed) == ["scaled", "src"]
    assert set(result.states) == {"src", "scaled"}


def test_parallel_run_gives_same_keys_and_content(numproject, tmp_path, log):
    serial = run(numproject)
    clone = tmp_path / "parallel"
    shutil.copytree(numproject, clone, ignore=shutil.ignore_patterns(".msflow"))
    parallel = run(clone, jobs=2)
    assert sorted(parallel.executed) == sorted(ALL)
    for name in ALL:
        assert parallel.key(name) == serial.key(name)
    worker_pids = {line.split()[1] for line in log.read_text().splitlines()[len(ALL) :]}
    assert worker_pids and str(os.getpid()) not in worker_pids  # executed in pool processes


def test_run_record_and_lock_file(numproject, log):
    result = run(numproject, "scaled.factor=4")
    record = result.record
    assert record["ok"] and record["counts"]["ran"] == len(ALL)
    assert record["overrides"] == ["scaled.factor=4"]
    assert record["stages"]["scaled"]["key_parts"]["params"] == {"factor": 4.0}
    assert record["stages"]["total"]["metrics"]["total"] == pytest.approx(expected_total(factor=4))
    assert "numpy" in record["versions"] and record["platform"]["cpus"]
    lock = (numproject / "pipeline.lock").read_text()
    assert "numstages.scaling:Scale" in lock and result.key("total") in lock
    before = (numproject / "pipeline.lock").stat().st_mtime_ns
    run(numproject, "scaled.factor=4")
    assert (numproject / "pipeline.lock").stat().st_mtime_ns == before  # unchanged state: not rewritten


def test_stage_resource_files_are_part_of_the_key(numproject, log):
    pipeline = numproject / "resources.yaml"
    first = msflow.run(pipeline)
    assert list(first.load("ref.v")) == [10.0, 20.0, 30.0]
    ref = numproject / "data" / "reference.txt"
    os.utime(ref, ns=(10**18, 10**18))
    assert msflow.run(pipeline).executed == []
    ref.write_text("1 2\n")
    from conftest import run_cli

    assert (
        "data file of the stage's code changed: resource ref"
        in run_cli(numproject, "why", "ref", "-f", "resources.yaml").stdout
    )
    again = msflow.run(pipeline)
    assert again.executed == ["ref"] and list(again.load("ref.v")) == [1.0, 2.0]


def test_folder_inputs_are_hashed_by_their_files(numproject, log):
    pipeline = numproject / "resources.yaml"
    assert msflow.run(pipeline).load("folder.total") == 6.0
    assert msflow.run(pipeline).executed == []
    (numproject / "data" / "parts" / "c.txt").write_text("4\n")
    result = msflow.run(pipeline)
    assert result.executed == ["folder"] and result.load("folder.total") == 10.0


def test_a_process_scans_its_installed_distributions_once_for_several_projects(numproject, tmp_path, log, monkeypatch):
    """A second project (its root now first on sys.path, its store fresh) maps its imports to distributions
    without scanning every installed distribution again (0.2-0.4 s), and gets the same keys."""
    import importlib.metadata

    first = run(numproject)
    scans = []
    real_scan = importlib.metadata.packages_distributions
    monkeypatch.setattr(importlib.metadata, "packages_distributions", lambda: scans.append(1) or real_scan())
    clone = tmp_path / "second"
    shutil.copytree(numproject, clone, ignore=shutil.ignore_patterns(".msflow"))
    second = run(clone)
    assert scans == [] and sorted(second.executed) == sorted(ALL)
    assert {n: second.key(n) for n in ALL} == {n: first.key(n) for n in ALL}


def fake_distribution(site: Path, version: str) -> None:
    """An installed distribution ``fakedist`` (module ``fakedist_mod``) in ``site``, as pip leaves it: upgrading
    replaces its .dist-info folder."""
    for old in site.glob("fakedist-*.dist-info"):
        shutil.rmtree(old)
    info = site / f"fakedist-{version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: fakedist\nVersion: {version}\n")
    (info / "top_level.txt").write_text("fakedist_mod\n")
    (site / "fakedist_mod.py").write_text("SCALE = 2.0\n")


def test_an_upgrade_in_a_virtualenv_inside_the_project_changes_the_keys(tmp_path):
    """A project with its virtualenv inside it (``.venv``): upgrading a package there changes the keys of the
    stages that import it, for the fast no-op path and for the planner alike."""
    from conftest import run_cli

    project = tmp_path / "proj"
    site = project / ".venv" / "lib" / "python3" / "site-packages"
    fake_distribution(site, "1.0")
    (project / "mystages").mkdir(parents=True)
    (project / "mystages" / "__init__.py").write_text("")
    (project / "mystages" / "scaled.py").write_text(
        "import numpy as np\nimport fakedist_mod\nfrom msflow import Stage, Output, Result\n\n"
        "class Scaled(Stage):\n    outputs = {'x': Output.array('f')}\n\n"
        "    def run(self, params, inputs):\n        return Result({'x': np.array([fakedist_mod.SCALE])})\n"
    )
    (project / "pipeline.yaml").write_text("version: 1\nstages:\n  s:\n    uses: mystages.scaled:Scaled\n")
    env = {"PYTHONPATH": str(site)}
    assert run_cli(project, "run", "-q", env=env).returncode == 0
    assert "1 cached, 0 to run" in run_cli(project, "status", env=env).stdout
    fake_distribution(site, "2.0")
    status = run_cli(project, "status", env=env)
    assert "0 cached, 1 to run" in status.stdout, status.stdout + status.stderr
    assert run_cli(project, "run", "-q", env=env).returncode == 0
    assert "1 cached, 0 to run" in run_cli(project, "status", env=env).stdout


def test_development_package_outside_the_project_is_fingerprinted(tmp_path):
    """Stages from a package installed for development (on sys.path, outside site-packages) count as code."""
    from conftest import run_cli

    pkg = tmp_path / "devsrc" / "devstages"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "mod.py").write_text(
        "import numpy as np\nfrom msflow import Stage, Output, Result\n\n"
        "class Const(Stage):\n    outputs = {'x': Output.array('f')}\n\n"
        "    def run(self, params, inputs):\n        return Result({'x': np.array([1.0])})\n"
    )
    project = tmp_path / "elsewhere"
    project.mkdir()
    (project / "pipeline.yaml").write_text("version: 1\nstages:\n  c:\n    uses: devstages.mod:Const\n")
    env = {"PYTHONPATH": str(tmp_path / "devsrc")}
    assert run_cli(project, "run", "-q", env=env).returncode == 0
    assert "1 cached, 0 to run" in run_cli(project, "status", env=env).stdout
    source = (pkg / "mod.py").read_text()
    (pkg / "mod.py").write_text("# a comment\n" + source)
    assert "1 cached, 0 to run" in run_cli(project, "status", env=env).stdout
    (pkg / "mod.py").write_text(source.replace("np.array([1.0])", "np.array([2.0])"))
    status = run_cli(project, "status", env=env).stdout
    assert "code: devstages/mod.py changed" in status


def test_parallel_workers_see_the_environment_of_each_run(numproject, tmp_path, monkeypatch):
    for i in range(2):  # a pool started by the first run must not freeze the environment for the second
        log_file = tmp_path / f"log{i}"
        monkeypatch.setenv("NUMSTAGES_LOG", str(log_file))
        msflow.run(numproject / "pipeline.yaml", overrides=[f"src.n={3 + i}"], jobs=2)
        assert "src" in executions(log_file)


def test_edit_in_a_clone_is_seen_although_the_original_is_unchanged(numproject, tmp_path, log):
    run(numproject)
    clone = tmp_path / "clone"
    shutil.copytree(numproject, clone)  # store and memo included
    assert run(clone).executed == []
    helper = clone / "numstages" / "helpers.py"
    helper.write_text(helper.read_text().replace("return 2 * np.asarray(x)", "return -2 * np.asarray(x)"))
    assert "scaled" in run(clone).executed
    assert run(numproject).executed == []


def test_memo_keeps_its_newest_entries_only(monkeypatch):
    from msflow import session as api

    monkeypatch.setattr(api, "MEMO_ENTRIES", 3)
    memo = {"params": {f"k{i}": i for i in range(5)}, "code": {"files": {"a": 1}}, "data": {}}
    api.trim_memo(memo)
    assert list(memo["params"]) == ["k2", "k3", "k4"] and memo["code"]["files"] == {"a": 1}
