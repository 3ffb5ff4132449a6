"""Where ``-j N`` runs each stage (msflow.executors.LocalExecutor): the run's own process first, for stages that
allow it (``Stage.in_process``); a worker process only when two stages are ready at once, never for a cheap stage
(``Stage.cheap``); stages that say nothing in workers, as before."""

import signal

import pytest
from conftest import Hold, run_cli, start_cli

import msflow
from msflow import executors

#: stages that log the process they ran in; ``Meet*`` wait (up to a minute) for each other to have started, so
#: they finish only if they run side by side
PLACED_STAGES = """
import os
import time

import numpy as np

from msflow import Input, Output, Result, Stage
from numstages.basic import hold_if_asked


def note(name):
    folder = os.environ["PLACED_LOG"]
    with open(os.path.join(folder, "log"), "a") as fh:
        fh.write(f"{name} {os.getpid()}\\n")
    open(os.path.join(folder, f"started.{name}"), "w").close()


def meet(name, other):
    note(name)
    deadline = time.monotonic() + 60  # a guard against hanging: alone, the stage fails
    while not os.path.exists(os.path.join(os.environ["PLACED_LOG"], f"started.{other}")):
        if time.monotonic() > deadline:
            raise RuntimeError(f"{other} never started beside {name}")
        time.sleep(0.01)


class Cheap(Stage):
    cheap = True
    inputs = {"x": Input.array("f", optional=True)}
    outputs = {"y": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        note(self.name)
        return Result({"y": np.zeros(2) if inputs.get("x") is None else inputs["x"] + 1})


class Long(Cheap):
    cheap = False
    in_process = True

    def run(self, params, inputs):
        note(self.name)
        time.sleep(0.2)  # long enough for the cheap stage beside it to be waiting
        return Result({"y": np.zeros(2) if inputs.get("x") is None else inputs["x"] + 1})


class MeetA(Long):
    def run(self, params, inputs):
        meet(self.name, "b")
        return Result({"y": np.zeros(2)})


class MeetB(Long):
    def run(self, params, inputs):
        meet(self.name, "a")
        return Result({"y": np.ones(2)})


class Held(Long):
    def run(self, params, inputs):
        note(self.name)
        try:
            hold_if_asked(self.name)
        finally:  # runs when the interrupt reaches the stage's thread: the stage unwinds as under -j 1
            open(os.path.join(os.environ["PLACED_LOG"], "unwound"), "w").close()
        return Result({"y": np.zeros(2)})
"""

PIPELINES = {
    "chain.yaml": """version: 1
stages:
  a: {uses: "numstages.placed:Cheap"}
  b: {uses: "numstages.placed:Long", inputs: {x: a.y}}
  c: {uses: "numstages.placed:Cheap", inputs: {x: b.y}}
""",
    "beside.yaml": """version: 1
stages:
  long: {uses: "numstages.placed:Long"}
  quick: {uses: "numstages.placed:Cheap"}
""",
    "meet.yaml": """version: 1
stages:
  a: {uses: "numstages.placed:MeetA"}
  b: {uses: "numstages.placed:MeetB"}
""",
    "held.yaml": """version: 1
stages:
  held: {uses: "numstages.placed:Held"}
""",
}


@pytest.fixture
def placed(numproject, tmp_path, monkeypatch):
    """The numeric test project with the stages above; returns (project, folder of their logs)."""
    (numproject / "numstages" / "placed.py").write_text(PLACED_STAGES)
    for name, text in PIPELINES.items():
        (numproject / name).write_text(text)
    logs = tmp_path / "logs"
    logs.mkdir()
    monkeypatch.setenv("PLACED_LOG", str(logs))
    return numproject, logs


def ran_in(logs):
    """Stage -> the pid of the process it ran in."""
    return {line.split()[0]: int(line.split()[1]) for line in (logs / "log").read_text().splitlines()}


@pytest.fixture
def no_workers(monkeypatch):
    """Any worker process the run starts fails the test."""

    def refuse(jobs):
        raise AssertionError("a worker process was started")

    monkeypatch.setattr(executors, "ProcessExecutor", refuse)


def test_a_chain_of_stages_that_allow_it_runs_in_the_runs_own_process(placed, no_workers):
    """A chain never has two stages ready at once: -j 2 runs all of it in the run's process, as -j 1 does, and
    starts no worker (each would import numpy, scipy, ... again)."""
    import os

    project, logs = placed
    result = msflow.run(project / "chain.yaml", jobs=2)
    assert result.executed == ["a", "b", "c"]
    assert set(ran_in(logs).values()) == {os.getpid()}
    assert result.load("c.y").tolist() == [2.0, 2.0]


def test_a_cheap_stage_waits_for_the_runs_process_instead_of_starting_a_worker(placed, no_workers):
    """A cheap stage ready while the run's process is on a long one waits for it: starting a worker for it would
    cost more than it saves."""
    import os

    project, logs = placed
    result = msflow.run(project / "beside.yaml", jobs=2)
    assert sorted(result.executed) == ["long", "quick"]
    assert ran_in(logs) == {"long": os.getpid(), "quick": os.getpid()}


def test_two_long_stages_ready_at_once_still_run_side_by_side(placed):
    """Each waits for the other to have started: they finish only if one runs in the run's process and the other
    in a worker at the same time."""
    import os

    project, logs = placed
    result = msflow.run(project / "meet.yaml", jobs=2)
    assert result.ok, result.states
    pids = ran_in(logs)
    assert os.getpid() in pids.values() and len(set(pids.values())) == 2


def test_stages_that_say_nothing_run_in_workers(placed):
    """Stages that do not allow it never run in the run's process under -j 2: a stage may start processes that a
    killed run could only stop in a worker's process group (tests/test_core_interrupt_children.py)."""
    import os

    project, _ = placed
    result = msflow.run(project / "pipeline.yaml", jobs=2)
    assert result.ok
    pids = {int(s["worker"].rsplit(" ", 1)[1]) for s in result.record["stages"].values()}
    assert os.getpid() not in pids


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupt_reaches_a_stage_in_the_runs_own_process(placed, tmp_path, signum, code):
    """Ctrl-C or SIGTERM while a stage runs in a thread of the run's process: the stage unwinds (its ``finally``
    runs) as under -j 1, the run says it was interrupted and exits, nothing partial is left, the next run goes
    on."""
    project, logs = placed
    hold = Hold(tmp_path / "hold")
    proc = start_cli(project, "run", "held.yaml", "-j", "2", env={**hold.env, "PLACED_LOG": str(logs)})
    name, pid = hold.wait_ready(proc).split()
    assert (name, int(pid)) == ("held", proc.pid)  # in the run's own process
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code and "interrupted: what finished is kept" in err, err
    assert "Traceback" not in err, err
    assert (logs / "unwound").exists()
    tmp = project / ".msflow" / "tmp"
    assert not tmp.exists() or list(tmp.iterdir()) == []
    hold.release()
    again = run_cli(project, "run", "held.yaml", "-j", "2", "-q", env={"PLACED_LOG": str(logs)})
    assert again.returncode == 0, again.stderr


def test_a_job_no_worker_can_be_started_for_fails_and_the_others_get_their_outcomes(monkeypatch):
    """A worker that cannot be started (a process limit, no memory: spawning raises) fails the job that was to run in
    it, which the runner reports as a lost worker; the stage whose thread was handing that job on (it ends, and the
    next waiting job starts from its thread) still gets its outcome. The thread died there, leaving its own stage's
    future unresolved: the run waited for it forever."""
    import errno
    import json
    import threading
    from concurrent.futures import Future

    from msflow import worker

    go = threading.Event()

    def run_job(job_json):
        go.wait()
        return "ran " + json.loads(job_json)["stage"]

    class OneProcess:
        """The first worker takes a job (that never finishes here); no other can be started."""

        made: list = []

        def __init__(self, jobs):
            self.made.append(self)

        def submit(self, job_json):
            if self is not self.made[0]:
                raise OSError(errno.EAGAIN, "Resource temporarily unavailable")
            return Future()

        def shutdown(self, *, abort=False):
            pass

    monkeypatch.setattr(worker, "run_job", run_job)
    monkeypatch.setattr(executors, "ProcessExecutor", OneProcess)
    local = executors.LocalExecutor(2)
    here = local.submit(json.dumps({"stage": "here", "in_process": True}))
    (thread,) = [t for t in threading.enumerate() if t.name == "msflow-stage"]
    local.submit(json.dumps({"stage": "in_a_worker"}))  # the one worker there is
    waiting = local.submit(json.dumps({"stage": "waiting"}))  # two running: it waits for a place
    go.set()
    thread.join()  # "here" is done; its thread started "waiting" in a new worker, which failed
    assert here.done() and here.result() == "ran here"
    assert isinstance(waiting.exception(timeout=0), OSError)
    failed = local.submit(json.dumps({"stage": "later"}))  # from the run's thread: no exception out of submit
    assert isinstance(failed.exception(timeout=0), OSError)
    local.shutdown()
