"""The ``msflow`` command line. Exit codes: 0 ok, 1 a stage failed (or an artifact is corrupt, or the disk is
full), 2 a user error (a message naming file, stage and field; no traceback), 141 its output was cut off (a pipe
closed early, as by ``msflow runs | head``), 130/143 interrupted (Ctrl-C / SIGTERM).

``main`` first asks the no-op fast path (``msflow.fastpath``) whether ``msflow run``/``msflow status`` has
nothing to do, which it answers from a compact state without importing typer, pydantic or any stage code; on any
doubt it falls back to the full commands in ``msflow.commands``.
"""

from __future__ import annotations

import errno
import sys


def main(argv: list[str] | None = None) -> int:
    """Run the ``msflow`` command line with ``argv`` (default: the process's arguments); returns the exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    from msflow.fastpath import try_noop

    try:
        code = try_noop(args)
        return run_commands(args) if code is None else code
    except BrokenPipeError:
        return _output_closed()


#: 128 + SIGPIPE: what a shell reports for `yes`, `cat` or `git log` whose reader went away (`set -o pipefail`,
#: PIPESTATUS); Python ignores SIGPIPE, so msflow says it with its exit code instead of dying of the signal
OUTPUT_CLOSED = 141


def _output_closed() -> int:
    """The reader of stdout went away (``msflow show aam | head``): stop quietly. What is still buffered goes to
    /dev/null, or Python's exit would try to flush it into the closed pipe and print "Exception ignored"."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return OUTPUT_CLOSED


def run_commands(args: list[str]) -> int:
    """The full command line (typer), errors mapped to exit codes without tracebacks."""
    import typer

    from msflow.commands import app, echo
    from msflow.errors import CorruptArtifact, StageFailed, UserError

    usage_errors = _usage_error_types()
    command = typer.main.get_command(app)
    terminated = _stop_on_sigterm()
    try:
        code = command.main(args=args, prog_name="msflow", standalone_mode=False)
        if isinstance(code, int):  # click returns typer.Exit's code instead of raising it here
            if code == INTERRUPTED:  # typer turns Ctrl-C (KeyboardInterrupt) into Exit(130), without a word
                return _interrupted(bool(terminated))
            return code
    except UserError as exc:
        echo(f"error: {exc}", err=True)
        return 2
    except (StageFailed, CorruptArtifact) as exc:
        echo(f"error: {exc}", err=True)
        return 1
    except typer.Exit as exc:
        return int(exc.exit_code)
    except SystemExit as exc:
        if isinstance(exc.__context__, BrokenPipeError):  # click turns a closed stdout into a bare exit 1
            return _output_closed()
        raise
    except typer.Abort:
        echo("aborted", err=True)
        return 130
    except usage_errors as exc:
        message = getattr(exc, "format_message", exc.__str__)()
        if message:  # none when click has shown the help instead (``msflow`` alone)
            echo(f"error: {message}", err=True)
        return 2
    except KeyboardInterrupt:
        return _interrupted(bool(terminated))
    except OSError as exc:
        if exc.errno not in _NO_ROOM:
            raise
        where = f" ({exc.filename})" if exc.filename else ""
        echo(f"error: cannot write{where}: {exc.strerror}; {_NO_ROOM[exc.errno]}", err=True)
        return 1
    return 0


INTERRUPTED = 130  # 128 + SIGINT, as shells report it
TERMINATED = 143  # 128 + SIGTERM


def _interrupted(by_sigterm: bool) -> int:
    """Say that the command was stopped and what that kept; the exit code a shell expects for the signal."""
    from msflow.commands import echo

    echo(
        "interrupted: what finished is kept (a stage cut short left nothing behind); the next run goes on from there",
        err=True,
    )
    return TERMINATED if by_sigterm else INTERRUPTED


#: a disk that cannot take more: what to tell the user (nothing half-written is ever used: see msflow.atomic)
_NO_ROOM = {
    errno.ENOSPC: "free some space (msflow gc drops the artifacts no recent run uses) and run again",
    errno.EDQUOT: "free some of your quota (msflow gc drops the artifacts no recent run uses) and run again",
    errno.EROFS: "the file system is read-only: put the store or the outputs elsewhere",
}


def _stop_on_sigterm() -> list[bool]:
    """Make SIGTERM (kill, docker stop, a batch system's time limit) stop a command as Ctrl-C does, so a run
    stops its workers and clears what they were writing instead of dying with them still at work; the list
    returned becomes [True] once it came."""
    import contextlib
    import signal

    came: list[bool] = []

    def interrupt(signum: int, frame: object) -> None:
        came.append(True)
        raise KeyboardInterrupt

    with contextlib.suppress(ValueError):  # not the main thread (msflow.cli.main called from a thread)
        signal.signal(signal.SIGTERM, interrupt)
    return came


def _usage_error_types() -> tuple[type[Exception], ...]:
    """Usage-error classes of the click that typer really uses (typer >= 0.26 vendors it as typer._click)."""
    found = []
    for module in ("typer._click.exceptions", "click.exceptions"):
        try:
            found.append(__import__(module, fromlist=["ClickException"]).ClickException)
        except ImportError:
            pass
    return tuple(found)


if __name__ == "__main__":
    sys.exit(main())
