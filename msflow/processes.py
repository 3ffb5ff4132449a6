"""Process lifetimes: a stopped run leaves no process behind, also none that a stage started inside a worker.

A worker of ``msflow.executors.ProcessExecutor`` leads its own process group (``lead_own_group``), so everything a
stage starts there (a process pool, FFmpeg, Node) is in that group, and stopping the run stops the whole group
(``stop_groups``) rather than the worker alone, which left its children running with no parent, holding the
run's stdout open. Processes that must not outlive the one that started them, should it be killed without a
chance to clean up (SIGKILL, the OOM killer), watch it (``exit_with_parent``).

POSIX only for process groups; elsewhere the workers alone are stopped, as before.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Sequence
from multiprocessing.process import BaseProcess

#: how long stopped workers get to exit after SIGTERM before their groups are killed
STOP_GRACE_SECONDS = 5.0
#: how often an orphan watch looks at its parent: a parent-death notice (Linux's PR_SET_PDEATHSIG) would be
#: immediate, but fires when the *thread* that started the process ends, which in a pool is not the parent's death
PARENT_POLL_SECONDS = 0.5

_GROUPS = hasattr(os, "setpgrp") and hasattr(os, "killpg")


def quiet_resource_tracker() -> None:
    """Start multiprocessing's resource tracker for this run (it is shared by every process spawned from here)
    without its leak warnings. Stopping a worker's group kills processes that still hold semaphores (a render
    pool's queues); the tracker removes those, as it should, and would then print "There appear to be 5 leaked
    semaphore objects" after msflow's own "interrupted" line. Nothing else leaks through it: msflow's processes
    hold no other tracked resources. No-op when the tracker already runs."""
    import sys
    from multiprocessing import resource_tracker

    saved = list(sys.warnoptions)
    sys.warnoptions.append("ignore::UserWarning")  # the tracker's command line repeats the interpreter's -W options
    try:
        resource_tracker.ensure_running()
    finally:
        sys.warnoptions[:] = saved


def lead_own_group() -> None:
    """Make this process the leader of a new process group that its children join (POSIX; no-op elsewhere).

    The terminal's Ctrl-C then no longer reaches it: the process that started it stops it (and its group)
    instead. It stays in the terminal's session, so it can still write there (it never reads stdin)."""
    if _GROUPS:
        os.setpgrp()


def exit_with_parent(parent_pid: int) -> None:
    """Watch (from a daemon thread) for this process's parent ``parent_pid`` to die; then exit at once, killing
    this process's group too when it leads one (the children it started would be orphans in turn)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_SECONDS)
        if _GROUPS and os.getpgrp() == os.getpid():
            os.killpg(os.getpid(), signal.SIGKILL)  # this process with them: its parent's run is gone
        os.kill(os.getpid(), signal.SIGKILL if hasattr(signal, "SIGKILL") else signal.SIGTERM)  # no cleanup: at once

    threading.Thread(target=watch, name="msflow-exit-with-parent", daemon=True).start()


def interrupt_thread(thread: threading.Thread) -> None:
    """Raise KeyboardInterrupt in ``thread`` at its next Python instruction, as Ctrl-C does in the main thread: a
    stage running there unwinds (its ``finally`` blocks stop what it started) instead of going on unseen."""
    import ctypes

    if thread.ident is not None and thread.is_alive():
        ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread.ident), ctypes.py_object(KeyboardInterrupt))


def stop_groups(processes: Sequence[BaseProcess], grace: float = STOP_GRACE_SECONDS) -> None:
    """Stop ``processes`` and the process groups they lead (``lead_own_group``): SIGTERM, then SIGKILL for what is
    left once they have exited or ``grace`` seconds have passed; reaps them. A process that leads no group (yet:
    it has not run its pool initializer) is signalled alone."""
    from multiprocessing.connection import wait

    for process in processes:
        _signal_group(process, hard=False)
    deadline = time.monotonic() + grace
    running = [p.sentinel for p in processes]
    while running and (left := deadline - time.monotonic()) > 0:  # ended or not, they are not reaped here
        ended = wait(running, timeout=left)
        running = [sentinel for sentinel in running if sentinel not in ended]
    for process in processes:
        _signal_group(process, hard=True)  # members that outlived SIGTERM, and the process if it did
    for process in processes:
        process.join()


def _signal_group(process: BaseProcess, *, hard: bool) -> None:
    """SIGTERM (``hard``: SIGKILL) the group ``process`` leads, or it alone when it leads none. A group's id is
    its leader's pid, which stays allocated while the leader is unreaped or any member lives: a group found by
    that id is the process's own."""
    if process.pid is None:
        return
    if _GROUPS:
        with contextlib.suppress(ProcessLookupError):  # no such group: the process did not make one
            os.killpg(process.pid, signal.SIGKILL if hard else signal.SIGTERM)
            return
    if hard:  # through the process object: it signals no pid it has reaped
        process.kill()
    else:
        process.terminate()
