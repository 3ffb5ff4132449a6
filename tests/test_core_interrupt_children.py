"""Ctrl-C (or SIGTERM) ends every process a run started, also those a stage started inside a worker: a stage's
process pool or helper program left running held the run's stdout open, so a caller reading it to its end hung."""

import contextlib
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import cli_env, process_running

#: stages that start children, each of which marks itself with a file ``child.<pid>``, then wait to be stopped:
#: Helpers starts a spawned process pool and a helper program that ignore SIGINT, as a render worker busy with a
#: block or an encoder finishing its file would; Preview renders a (slow, endless) preview with worker processes
CHILDREN_STAGES = """
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from msflow import Output, Result, Stage
from stages.export.preview import Poses, rendered_frames

HELPER = "import signal, time\\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\\nwhile True:\\n    time.sleep(1)\\n"


def mark_child(pid):
    open(os.path.join(os.environ["CHILDREN_FOLDER"], f"child.{pid}"), "w").close()


def ignore_interrupts():
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class Helpers(Stage):
    outputs = {"x": Output.array("f")}

    def run(self, params, inputs):
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(1, mp_context=context, initializer=ignore_interrupts) as pool:
            helper = subprocess.Popen([sys.executable, "-c", HELPER])
            try:
                mark_child(pool.submit(os.getpid).result())
                mark_child(helper.pid)
                while True:  # until the run is stopped
                    time.sleep(0.05)
            finally:
                helper.kill()
                helper.wait()
        return Result({"x": np.zeros(1)})


class SlowRenderer:
    def __call__(self, weights, rotation, translation, eye_rotations):
        if not os.path.exists(os.path.join(os.environ["CHILDREN_FOLDER"], f"child.{os.getpid()}")):
            mark_child(os.getpid())
        time.sleep(0.01)  # a frame's drawing
        return np.zeros((2, 2, 3), np.uint8)


class Preview(Stage):
    outputs = {"x": Output.array("f")}

    def run(self, params, inputs):
        poses = Poses(np.zeros((1_000_000, 1)))  # longer than any test
        for _ in rendered_frames(SlowRenderer(), poses, jobs=2, block=4, processes=True):
            pass
        return Result({"x": np.zeros(1)})
"""


def children_project(tmp_path, stage):
    project = tmp_path / "proj"
    (project / "kidstages").mkdir(parents=True)
    (project / "kidstages" / "__init__.py").write_text("")
    (project / "kidstages" / "children.py").write_text(CHILDREN_STAGES)
    pipeline = f"version: 1\nstages:\n  parent:\n    uses: kidstages.children:{stage}\n"
    (project / "pipeline.yaml").write_text(pipeline)
    return project


def wait_for(condition, timeout, what):
    deadline = time.monotonic() + timeout  # a guard against hanging, not a speed assertion
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def child_pids(folder):
    return [int(path.suffix[1:]) for path in folder.glob("child.*")]


@pytest.mark.parametrize(
    ("stage", "jobs", "signum", "to_group"),
    [
        ("Helpers", "1", signal.SIGINT, False),
        ("Helpers", "1", signal.SIGINT, True),
        ("Helpers", "2", signal.SIGINT, False),
        ("Helpers", "2", signal.SIGINT, True),
        ("Helpers", "2", signal.SIGTERM, False),
        ("Helpers", "2", signal.SIGKILL, False),
        ("Preview", "1", signal.SIGINT, False),
        ("Preview", "1", signal.SIGINT, True),
        ("Preview", "2", signal.SIGINT, False),
        ("Preview", "2", signal.SIGINT, True),
    ],
)
def test_stopping_a_run_ends_the_processes_its_stages_started(tmp_path, stage, jobs, signum, to_group):
    """Ctrl-C (SIGINT to the terminal's process group, or to msflow alone) or SIGTERM in the middle of a stage
    that started a process pool and a helper program, or that renders a preview with worker processes: msflow says
    it was interrupted and exits, and no child outlives it, with -j 1 (the stage runs in msflow) and -j 2 (in a
    worker msflow stops). Killed (SIGKILL), msflow says nothing, but its workers and their children go too."""
    project = children_project(tmp_path, stage)
    folder = tmp_path / "children"
    folder.mkdir()
    run = subprocess.Popen(
        [sys.executable, "-m", "msflow.cli", "run", "-j", jobs],
        cwd=project,
        env=cli_env({"CHILDREN_FOLDER": str(folder)}),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a shell gives a command: Ctrl-C reaches the group
    )
    try:
        started = lambda: len(child_pids(folder)) >= 2 or run.poll() is not None
        wait_for(started, 120, "the stage to start its children")
        assert run.poll() is None, run.communicate()
        (os.killpg if to_group else os.kill)(run.pid, signum)
        run.wait(timeout=60)
        wait_for(lambda: not any(process_running(pid) for pid in child_pids(folder)), 10, "the stage's children to end")
        _, err = run.communicate(timeout=10)  # the children held its pipes open: a caller reading them hung
        if signum == signal.SIGKILL:
            assert run.returncode == -signal.SIGKILL
        else:
            assert run.returncode == 128 + signum and "interrupted: what finished is kept" in err, err
            assert "Traceback" not in err and "leaked" not in err, err  # nor the resource tracker's cleanup
    finally:
        for pid in child_pids(folder):  # whatever this test left running
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(OSError):
            os.killpg(run.pid, signal.SIGKILL)
        run.kill()
        run.wait()
        for pipe in (run.stdout, run.stderr):
            pipe.close()
