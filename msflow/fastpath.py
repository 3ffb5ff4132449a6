"""The no-op fast path: ``msflow run`` and ``msflow status`` answer "nothing to do" from a compact state.

After a full ``msflow run`` in which every stage is done (on a local store, without ``--until`` or ``--force``),
the runner saves what that answer depends on: the stat signatures of the pipeline file, its lock, every code file
and folder of the stages' import closures, every data file and folder read (and the folders globs listed), every
published file, and each stage artifact's manifest; plus the environment (Python, msflow's own files, the
folders on ``sys.path``). The next ``msflow run``/``status`` with the same pipeline file and ``-S`` overrides stats
those paths and, when every signature is equal, prints what the full path would print (each stage cached, the
warnings of cached stages, the published files as up to date) and writes a small run record pointing at the full one.

It imports only the standard library (no typer, pydantic, yaml, numpy or stage code). Any doubt - an option it
does not know, a missing or unreadable state, one changed signature - hands over to the full path, which
recomputes keys and decides (and saves a fresh state). MSFLOW_FASTPATH_DEBUG=1 prints why it handed over;
MSFLOW_FASTPATH=0 turns it off.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from typing import Any

from msflow.syspath import in_project

FORMAT = 2  # 2: the pipeline's warnings (msflow.variables), printed first
RUN_FLAGS = {"-q", "--quiet"}
VALUED = {"-S": "set", "--set": "set", "-j": "jobs", "--jobs": "jobs", "--executor": "executor"}
VALUED.update({"--connect-timeout": "timeout"})
FILE_OPTIONS = {"-f", "--file"}


def signature(path: str) -> str:
    """(size, mtime_ns, inode) of a file or folder, or "missing": what must stay equal for a state to hold."""
    try:
        st = os.stat(path)
    except OSError:
        return "missing"
    return f"{st.st_size}:{st.st_mtime_ns}:{st.st_ino}"


def listing(path: str) -> str:
    """ "ls:" + digest of the Python modules and packages in a code folder: what imports can resolve to (its mtime
    also moves when __pycache__ or a lock file is written, which changes no import)."""
    try:
        names = sorted(
            e.name
            for e in os.scandir(path)
            if not e.name.startswith(".") and e.name != "__pycache__" and (e.name.endswith(".py") or e.is_dir())
        )
    except OSError:
        return "missing"
    return "ls:" + hashlib.sha1(json.dumps(names).encode()).hexdigest()[:20]


def current(path: str, expected: str) -> str:
    """The value to compare with a saved one: a folder listing for "ls:" entries, else the stat signature."""
    return listing(path) if expected.startswith("ls:") else signature(path)


def state_file(pipeline: str, overrides: list[str]) -> str:
    """Where the state of ``msflow run PIPELINE -S ...`` lives: beside the pipeline, in .msflow/cache/fast/."""
    digest = hashlib.sha1(json.dumps([pipeline, overrides]).encode()).hexdigest()[:20]
    return os.path.join(os.path.dirname(pipeline), ".msflow", "cache", "fast", f"{digest}.json")


def environment(project_root: str) -> str:
    """Digest of what the interpreter brings: Python, msflow's own source files, and the folders on sys.path
    outside the project or holding installed packages (an installed or removed package changes its folder's
    mtime; a virtualenv inside the project too)."""
    package = os.path.dirname(os.path.abspath(__file__))  # msflow/
    sources = []
    for folder, dirs, files in os.walk(package):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        sources += [[name, signature(os.path.join(folder, name))] for name in sorted(files) if name.endswith(".py")]
    root = project_root.rstrip(os.sep) + os.sep
    path = [[p, signature(p)] for p in sys.path if not in_project(p, [root])]
    text = json.dumps([sys.version, sys.executable, sources, path])
    return hashlib.sha1(text.encode()).hexdigest()


# ---------------------------------------------------------------------------------------------------------- reading
def parse_args(args: list[str]) -> tuple[str, str, list[str], bool] | None:
    """(command, absolute pipeline file, overrides, quiet) of a plain ``run`` or ``status``; None otherwise."""
    if not args or args[0] not in ("run", "status"):
        return None
    command, rest = args[0], args[1:]
    file, overrides, quiet = None, [], False
    i = 0
    while i < len(rest):
        arg = rest[i]
        name, eq, inline = arg.partition("=") if arg.startswith("--") else (arg, "", "")
        if command == "run" and arg in RUN_FLAGS:
            quiet = True
        elif name in VALUED and (command == "run" or VALUED[name] == "set"):
            i, value = option_value(rest, i, inline if eq else None)
            if value is None or not valid_option(VALUED[name], value):
                return None
            if VALUED[name] == "set":
                overrides.append(value)
        elif arg.startswith("-S") and len(arg) > 2:
            overrides.append(arg[2:])
        elif name in FILE_OPTIONS:  # -f FILE: the FILE argument's other form (msflow.commands)
            i, value = option_value(rest, i, inline if eq else None)
            if value is None or file is not None:
                return None
            file = value
        elif arg.startswith("-") or file is not None:
            return None
        else:
            file = arg
        i += 1
    path = os.path.abspath(file or "pipeline.yaml")
    return (command, path, overrides, quiet) if os.path.isfile(path) else None


def option_value(rest: list[str], i: int, inline: str | None) -> tuple[int, str | None]:
    """(index of the option's last word, its value) for the option at ``rest[i]``: ``inline`` (``--name=value``)
    or the next word (None when there is none)."""
    if inline is not None:
        return i, inline
    return i + 1, rest[i + 1] if i + 1 < len(rest) else None


def valid_option(kind: str, value: str) -> bool:
    """Whether an option value is one the full path accepts too (it reports the errors)."""
    if kind == "jobs":
        return value.isdigit() and int(value) >= 1
    if kind == "executor":
        return value in ("local", "dask")
    if kind == "timeout":
        try:
            return float(value) > 0
        except ValueError:
            return False
    return "=" in value


def load_state(pipeline: str, overrides: list[str]) -> dict[str, Any] | None:
    """The saved state when every signature in it still holds, else None (MSFLOW_FASTPATH_DEBUG=1 says why)."""
    try:
        with open(state_file(pipeline, overrides), encoding="utf-8") as fh:
            state = json.load(fh)
    except (OSError, ValueError):
        doubt("no saved state")
        return None
    if not isinstance(state, dict) or state.get("format") != FORMAT or state.get("pipeline") != pipeline:
        doubt("the saved state is of another format or pipeline")
        return None
    watch = state.get("watch")
    if not isinstance(watch, dict):
        doubt("the saved state has no signatures")
        return None
    for path, sig in watch.items():
        if current(path, sig) != sig:
            doubt(f"{path} changed")
            return None
    if state.get("environment") != environment(state.get("root", "")):
        doubt("the environment changed (Python, msflow, or a folder on sys.path)")
        return None
    return state


def doubt(reason: str) -> None:
    """Give up the fast path (the full path decides), saying why when MSFLOW_FASTPATH_DEBUG is set."""
    if os.environ.get("MSFLOW_FASTPATH_DEBUG"):
        print(f"msflow fast path: {reason}", file=sys.stderr)
    return None


def try_noop(args: list[str]) -> int | None:
    """Exit code of ``msflow ARGS`` when it is a no-op ``run`` or ``status`` answered from the saved state;
    None (use the full path) on any doubt."""
    if os.environ.get("MSFLOW_FASTPATH") == "0":  # benchmarks and debugging: always the full path
        return None
    try:
        parsed = parse_args(args)
        if parsed is None:
            doubt("not a plain run or status")
            return None
        command, pipeline, overrides, quiet = parsed
        started = time.time()
        state = load_state(pipeline, overrides)
        if state is None:
            return None
        run_id = None if command == "status" else write_small_record(state, args, overrides, started)
    except Exception as exc:  # nothing printed yet: the full path decides
        doubt(f"{type(exc).__name__}: {exc}")
        return None
    # printing comes after the doubts: a closed stdout (`msflow status | head`) must not make the full path
    # compute the answer again
    if run_id is None:
        print_status(state)
    else:
        print_run(state, run_id, quiet, time.time() - started)
    return 0


# ---------------------------------------------------------------------------------------------------------- output
def print_status(state: dict[str, Any]) -> None:
    stages = state["stages"]
    width = max(len(n) for n in stages)
    for name in stages:
        print(f"{name:<{width}}  cached")
    print(f"{len(stages)} cached, 0 to run", flush=True)


def print_warnings(messages: list[str]) -> None:
    """``warning: ...`` lines on stderr, yellow on a terminal, as the full path prints them."""
    colour = sys.stderr.isatty()
    for message in messages:
        line = f"warning: {message}"
        print(f"\033[33m{line}\033[0m" if colour else line, file=sys.stderr)


def print_run(state: dict[str, Any], run_id: str, quiet: bool, seconds: float) -> None:
    """What the full path prints for a run where every stage is cached (plain progress lines on stderr)."""
    stages = state["stages"]
    print_warnings(state.get("pipeline_warnings", []))  # before the stages, as the full path prints them
    if not quiet:
        width = max((len(n) for n in stages), default=8)
        for name in stages:
            print(f"= {name:<{width}}  cached  ", file=sys.stderr)
        print(f"{len(stages)} cached in {seconds:.2f}s (run {run_id})", file=sys.stderr)
    warnings = [
        f"{stage} (cached result): {m}" for stage, messages in state.get("warnings", {}).items() for m in messages
    ]
    print_warnings(warnings + state.get("summary_warnings", []))
    sys.stderr.flush()
    from msflow.summary import published_lines

    # every published file's signature held, so none was written: all are up to date, as a full no-op says
    for line in published_lines(state.get("published", []), []) + state.get("summary", []):
        print(line)
    sys.stdout.flush()


def write_small_record(state: dict[str, Any], args: list[str], overrides: list[str], started: float) -> str:
    """The run's small record (``same_as`` the full record that describes the same state); returns its id."""
    from msflow.atomic import write_json_atomic
    from msflow.stores.base import new_run_id

    run_id = new_run_id()
    counts = {"cached": len(state["stages"]), "ran": 0, "failed": 0, "skipped": 0}
    record = {
        "id": run_id,
        "same_as": state["same_as"],
        "pipeline": state["rel_pipeline"],
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started)),
        "seconds": round(time.time() - started, 6),
        "ok": True,
        "executor": "none",
        "jobs": 1,
        "argv": args,
        "overrides": overrides,
        "variant": {},
        "counts": counts,
    }
    runs = state["runs"]
    os.makedirs(runs, exist_ok=True)
    write_json_atomic(os.path.join(runs, f"{run_id}.json"), record, indent=1)
    return run_id


# ---------------------------------------------------------------------------------------------------------- writing
def save_state(
    pipeline: str,
    overrides: list[str],
    root: str,
    watch: dict[str, str],
    stages: list[str],
    warnings: dict[str, list[str]],
    same_as: str,
    runs: str,
    rel_pipeline: str,
    summary: tuple[list[str], list[str]] = ([], []),
    published: list[str] | None = None,
    pipeline_warnings: list[str] | None = None,
) -> None:
    """Save the state a later no-op ``run``/``status`` with the same pipeline and overrides answers from."""
    from msflow.atomic import write_json_atomic

    state = {
        "format": FORMAT,
        "pipeline": pipeline,
        "overrides": overrides,
        "root": root,
        "environment": environment(root),
        "watch": watch,
        "stages": stages,
        "warnings": warnings,
        "same_as": same_as,
        "runs": runs,
        "rel_pipeline": rel_pipeline,
        "summary": summary[0],
        "summary_warnings": summary[1],
        "published": published or [],
        "pipeline_warnings": pipeline_warnings or [],
    }
    path = state_file(pipeline, overrides)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    write_json_atomic(path, state)
