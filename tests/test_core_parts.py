"""Parts (msflow.parts, Stage.part): a stage over labelled takes stores each take's piece on its own, so adding
a take computes only the new one; the result is the same as a run from scratch, damaged parts are recomputed,
and gc keeps the parts the kept artifacts were built from."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import Hold, executions, run_cli, start_cli, wait_for_line

import msflow
from msflow.gc import collect_garbage
from msflow.stores import open_store
from msflow.testing import run_stage


@pytest.fixture
def log(tmp_path, monkeypatch):
    path = tmp_path / "executions.log"
    monkeypatch.setenv("NUMSTAGES_LOG", str(path))
    return path


def write_takes(proj: Path, **takes: list[float]) -> None:
    folder = proj / "takes"
    folder.mkdir(exist_ok=True)
    for name, values in takes.items():
        (folder / f"{name}.txt").write_text("\n".join(map(str, values)) + "\n")


def parts_computed(log: Path) -> list[str]:
    return sorted(line.split()[1] for line in log.read_text().splitlines() if line.startswith("part "))


def run(proj: Path, *overrides: str):
    return msflow.run(proj / "parts.yaml", overrides=overrides)


def parts_manifest(execution) -> dict:
    return execution.states["per_take"].manifest["parts"]


def test_adding_a_take_computes_only_its_part_across_processes(numproject, tmp_path):
    log = tmp_path / "cli.log"
    env = {"NUMSTAGES_LOG": str(log)}
    write_takes(numproject, a=[1, 2], b=[3])
    first = run_cli(numproject, "run", "parts.yaml", env=env)
    assert first.returncode == 0, first.stderr
    assert parts_computed(log) == ["a.txt", "b.txt"]
    log.unlink()
    write_takes(numproject, c=[4, 5, 6])
    second = run_cli(numproject, "run", "parts.yaml", env=env)
    assert second.returncode == 0, second.stderr
    assert executions(log) == ["per_take", "part"]  # the stage ran, and computed one part
    assert parts_computed(log) == ["c.txt"]
    assert "2 of 3 parts reused" in second.stdout + second.stderr
    shown = run_cli(numproject, "show", "per_take", "parts.yaml")
    assert "built from 3 parts, 2 found stored when it ran" in shown.stdout


def test_a_result_built_from_stored_parts_equals_one_computed_whole(numproject, tmp_path, log):
    write_takes(numproject, a=[1, 2], b=[3])
    run(numproject)
    write_takes(numproject, c=[4, 5, 6])
    grown = run(numproject)
    assert parts_manifest(grown)["reused"] == ["a.txt", "b.txt"]
    fresh_proj = tmp_path / "fresh"
    shutil.copytree(numproject, fresh_proj, ignore=shutil.ignore_patterns(".msflow", "__pycache__"))
    fresh = run(fresh_proj)
    assert parts_manifest(fresh)["reused"] == []
    assert grown.states["per_take"].manifest["content_hash"] == fresh.states["per_take"].manifest["content_hash"]
    np.testing.assert_array_equal(grown.load("per_take.values"), [1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(grown.load("per_take.take"), [0, 0, 1, 2, 2, 2])


def test_what_a_part_reads_decides_whether_it_is_reused(numproject, log):
    write_takes(numproject, a=[1, 2], b=[3])
    run(numproject)
    log.unlink()
    (numproject / "takes" / "b.txt").rename(numproject / "takes" / "renamed.txt")
    renamed = run(numproject)  # a new label for the same content: its part is the same
    assert "per_take" in renamed.executed and parts_computed(log) == []
    write_takes(numproject, a=[1, 7])
    run(numproject)
    assert parts_computed(log) == ["a.txt"]  # its content changed: only its part is computed again
    log.unlink()
    run(numproject, "per_take.scale=2")
    assert parts_computed(log) == ["a.txt", "renamed.txt"]  # params reach every part
    log.unlink()
    commented = run(numproject, "per_take.scale=2", "per_take.comment=new")
    assert "per_take" in commented.executed and parts_computed(log) == []  # but those no part reads


def test_a_whole_input_reaches_every_part(numproject, log):
    write_takes(numproject, a=[1], b=[2])
    (numproject / "offset.txt").write_text("10\n")
    spec = (numproject / "parts.yaml").read_text()
    (numproject / "parts.yaml").write_text(spec.replace('"takes/*.txt"}', '"takes/*.txt"}, offset: {path: offset.txt}'))
    run(numproject)
    log.unlink()
    (numproject / "offset.txt").write_text("20\n")
    again = run(numproject)
    assert parts_computed(log) == ["a.txt", "b.txt"]
    np.testing.assert_array_equal(again.load("per_take.values"), [21, 22])


def test_a_damaged_part_is_set_aside_and_computed_again(numproject, log):
    write_takes(numproject, a=[1, 2, 3], b=[4])
    first = run(numproject)
    key = parts_manifest(first)["keys"]["a.txt"]
    store = open_store(str(numproject / ".msflow"))
    chunk = max((p for p in store.artifact_path(key).rglob("c/*") if p.is_file()), key=lambda p: p.stat().st_size)
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x10
    chunk.write_bytes(bytes(data))
    log.unlink()
    write_takes(numproject, c=[5])
    second = run(numproject)
    assert parts_computed(log) == ["a.txt", "c.txt"]
    assert any("part of 'a.txt' was damaged" in w for w in second.states["per_take"].manifest["warnings"])
    np.testing.assert_array_equal(second.load("per_take.values"), [1, 2, 3, 4, 5])
    assert store.verify(key) == []


def test_gc_keeps_the_parts_of_kept_artifacts_and_drops_the_rest(numproject, log):
    write_takes(numproject, a=[1], b=[2])
    first = run(numproject)
    old_b = parts_manifest(first)["keys"]["b.txt"]
    write_takes(numproject, b=[9])
    second = run(numproject)
    kept = set(parts_manifest(second)["keys"].values())
    store = open_store(str(numproject / ".msflow"))
    result = collect_garbage(store, keep_runs=1)
    assert all(store.has(k) for k in kept)
    assert not store.has(old_b) and old_b in result["artifacts"]


def test_outside_a_store_parts_are_computed_in_memory(tmp_path, log, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent / "numproject"))
    from numstages.basic import PerTake

    write_takes(tmp_path, a=[1, 2], b=[3])
    out = run_stage(PerTake, {"scale": 2}, {"takes": {p.stem: p for p in sorted((tmp_path / "takes").iterdir())}})
    np.testing.assert_array_equal(out.arrays["values"], [2, 4, 6])
    assert parts_computed(log) == ["a.txt", "b.txt"]


def test_a_part_names_only_declared_inputs():
    from msflow import Input, Output, Result, Stage

    class Bad(Stage):
        inputs = {"takes": Input.files(), "x": Input.array("f")}
        outputs = {"y": Output.array("f")}

        def run(self, params, inputs):
            return Result({"y": np.zeros(1)})

    stage = Bad("bad")
    with pytest.raises(ValueError, match="unknown inputs"):
        stage.part("a", lambda sink: None, labelled=("clips",))
    with pytest.raises(ValueError, match="must be files inputs"):
        stage.part("a", lambda sink: None, labelled=("x",))
    with pytest.raises(ValueError, match="unread_params .'n'. are no params"):
        stage.part("a", lambda sink: None, labelled=("takes",), unread_params=("n",))


def test_force_computes_every_part_again(numproject, log):
    write_takes(numproject, a=[1, 2], b=[3])
    run(numproject)
    log.unlink()
    forced = msflow.run(numproject / "parts.yaml", force=("per_take",))
    assert parts_computed(log) == ["a.txt", "b.txt"]
    assert parts_manifest(forced)["reused"] == []


def test_two_runs_needing_one_part_compute_it_once(numproject, tmp_path):
    """Two pipelines with different stage keys share the part of one video: the second waits for the first's."""
    log = tmp_path / "cli.log"
    write_takes(numproject, a=[1, 2], b=[3])
    spec = (numproject / "parts.yaml").read_text()
    (numproject / "one.yaml").write_text(spec.replace('{glob: "takes/*.txt"}', "{first: takes/a.txt}"))
    hold = Hold(tmp_path / "hold")
    holder = start_cli(numproject, "run", "parts.yaml", "-q", env={**hold.env, "NUMSTAGES_LOG": str(log)})
    assert hold.wait_ready(holder).startswith("part a.txt")
    waiter = start_cli(numproject, "run", "one.yaml", "-q", env={"NUMSTAGES_LOG": str(log)})
    wait_for_line(waiter, "part 'first' is being computed by another run")
    hold.release()
    assert holder.wait() == 0 and waiter.wait() == 0
    assert parts_computed(log) == ["a.txt", "b.txt"]
    one = msflow.run(numproject / "one.yaml")
    assert one.executed == [] and parts_manifest(one)["reused"] == ["first"]


def test_a_parts_warnings_are_said_again_when_it_is_reused(numproject, log):
    """A take that warns while its part is computed (an empty file: numpy's loadtxt warns) warns again when a later
    run finds its part stored: the stage's warnings, and so its content hash, do not depend on which parts an
    earlier run had computed."""
    write_takes(numproject, a=[1, 2])
    (numproject / "takes" / "empty.txt").write_text("")
    first = run(numproject)
    said = first.states["per_take"].manifest["warnings"]
    assert any("empty.txt" in w for w in said), said
    write_takes(numproject, c=[3])
    grown = run(numproject)
    assert parts_manifest(grown)["reused"] == ["a.txt", "empty.txt"]
    forced = msflow.run(numproject / "parts.yaml", force=("per_take",))  # every part computed, in this folder
    assert parts_manifest(forced)["reused"] == []
    assert grown.states["per_take"].manifest["warnings"] == said
    assert grown.states["per_take"].manifest["content_hash"] == forced.states["per_take"].manifest["content_hash"]


def test_a_new_key_scheme_computes_the_parts_again(numproject, log, monkeypatch):
    """A key scheme bump (msflow.version.KEY_SCHEME: a change that alters stored results) makes every stage key
    new; the parts' keys must change with it, or the new stage artifact is built from parts of the old scheme."""
    import msflow.runner

    write_takes(numproject, a=[1, 2], b=[3])
    first = run(numproject)
    log.unlink()
    monkeypatch.setattr(msflow.runner, "KEY_SCHEME", msflow.runner.KEY_SCHEME + 1)
    again = run(numproject)
    assert again.executed == ["per_take"]
    assert parts_manifest(again)["reused"] == [] and parts_computed(log) == ["a.txt", "b.txt"]
    assert set(parts_manifest(again)["keys"].values()).isdisjoint(parts_manifest(first)["keys"].values())


def test_a_label_has_one_part(tmp_path):
    """A second part of one label would share the first's key (the key names the label's inputs, not the function
    computing it) and be handed the first's content: it is an error, in a store run and outside one alike."""
    from msflow import Input, Output, Result, Stage

    class Twice(Stage):
        inputs = {"takes": Input.files()}
        outputs = {"y": Output.array("f")}

        def run(self, params, inputs):
            label = next(iter(inputs["takes"]))
            ones = self.part(label, lambda sink: Result({"y": np.ones(2)}), labelled=("takes",))
            twos = self.part(label, lambda sink: Result({"y": np.full(2, 2.0)}), labelled=("takes",))
            return Result({"y": np.concatenate([ones.arrays["y"], twos.arrays["y"]])})

    take = tmp_path / "a.txt"
    take.write_text("1\n")
    with pytest.raises(ValueError, match="part 'a' is asked for twice"):
        run_stage(Twice, {}, {"takes": {"a": take}})
