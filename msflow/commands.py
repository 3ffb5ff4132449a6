"""The ``msflow`` commands (typer); ``msflow.cli.main`` is the entry point that runs them."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, List, Optional

import typer

from msflow.errors import UserError, display_path
from msflow.jobs import DryStatus, StageStatus

if TYPE_CHECKING:
    from msflow.artifact import ArtifactView
    from msflow.stores.base import Store
    from msflow.sweep import SweepResult

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="msflow: cached dataflow pipelines (Mood Swings expressive speech animation).",
)

# Every command that reads a pipeline takes its file the same way: as its last argument (FILE, as in `msflow run
# pipeline.yaml`), or as -f/--file FILE, which some commands had before the argument and scripts still use.
FILE_ARG = typer.Argument(None, help="pipeline file (or -f FILE)", show_default="pipeline.yaml")
FILE_OPT = typer.Option(None, "-f", "--file", help="pipeline file, the same as the FILE argument", show_default=False)
DEFAULT_FILE = Path("pipeline.yaml")


def given_pipeline_file(argument: Path | None, option: Path | None) -> Path | None:
    """The pipeline file given as the FILE argument or with -f/--file (None: neither); both is an error unless
    they name the same file."""
    if argument is not None and option is not None and argument.resolve() != option.resolve():
        raise UserError(f"two pipeline files, {argument} and -f {option}: give one", field="FILE")
    return argument or option


def pipeline_file(argument: Path | None, option: Path | None) -> Path:
    """The pipeline file a command reads: the one given (``given_pipeline_file``), else pipeline.yaml."""
    return given_pipeline_file(argument, option) or DEFAULT_FILE


def _print_version(asked: bool) -> None:
    if asked:
        from msflow.version import package_version

        echo(f"msflow {package_version()}")
        raise typer.Exit(0)


@app.callback()
def main_options(
    version: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="print msflow's version and exit"
    ),
) -> None:
    """msflow: cached dataflow pipelines (Mood Swings expressive speech animation)."""


def echo(text: str = "", err: bool = False) -> None:
    print(text, file=sys.stderr if err else sys.stdout, flush=True)


def _split(values: list[str] | None) -> tuple[str, ...]:
    return tuple(v for item in values or () for v in item.split(",") if v)


# ---------------------------------------------------------------------------------------------------------- run
@app.command()
def run(
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    until: Optional[str] = typer.Option(None, "--until", help="run only this stage and what it needs"),
    force: Optional[List[str]] = typer.Option(None, "--force", help="rerun these stages even if cached"),
    overrides: Optional[List[str]] = typer.Option(None, "-S", "--set", help="stage.param=value override"),
    jobs: int = typer.Option(1, "-j", "--jobs", help="stages to run at once (msflow's process and worker processes)"),
    executor: str = typer.Option("local", "--executor", help="local or dask"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address tcp://host:port"),
    connect_timeout: float = typer.Option(10.0, "--connect-timeout", help="seconds to reach the scheduler"),
    quiet: bool = typer.Option(False, "-q", "--quiet", help="no progress display"),
    publish_dir: Optional[Path] = typer.Option(
        None, "--publish-dir", help="publish into this folder (may be outside the project) instead of beside the file"
    ),
) -> None:
    """Run the pipeline: compute what is missing, reuse everything else."""
    from msflow.api import run as run_pipeline
    from msflow.progress import make_reporter
    from msflow.session import open_session

    file = pipeline_file(file, file_option)
    session = open_session(file, tuple(overrides or ()), publish_dir=publish_dir)
    for warning in session.pipeline.warnings:  # before the run: the user may want to stop it and rename
        _warn(warning)
    reporter = make_reporter(list(session.plans), quiet)
    if reporter:
        reporter.start()
    try:
        result = run_pipeline(
            file,
            session=session,
            jobs=jobs,
            until=until,
            force=_split(force),
            executor=executor,
            scheduler=scheduler,
            reporter=reporter,
            argv=sys.argv[1:],
            raise_on_failure=False,
            connect_timeout=connect_timeout,
            publish_dir=publish_dir,
        )
    finally:
        if reporter:
            reporter.stop()
    counts = result.record["counts"]
    summary = ", ".join(f"{v} {k}" for k, v in counts.items() if v)
    if not quiet:
        ran = [s.cpu_seconds for s in result.states.values() if s.state is StageStatus.RAN]
        cpu = f", stages {sum(ran):.2f}s CPU" if ran else ""
        echo(f"{summary or 'nothing selected'} in {result.record['seconds']:.2f}s{cpu} (run {result.run_id})", err=True)
    _echo_warnings(result.warnings, {n: s.state for n, s in result.states.items()})
    for repair in result.record.get("repairs", []):
        where = f"; moved aside to {display_path(repair['moved_to'])}" if repair.get("moved_to") else ""
        _warn(
            f"{repair['stage']}: its artifact {repair['key'][:12]} was corrupt ({repair['problem']}){where}; recomputed"
        )
    for warning in result.publish_warnings:
        _warn(warning)
    _echo_summary(result.session.pipeline.summary, result.record["stages"], result.published, result.newly_published)
    for name, state in result.states.items():
        if state.state is StageStatus.FAILED and not state.user_error and state.traceback:
            echo(f"\n--- stage '{name}' failed; traceback (also in the run record):", err=True)
            echo(state.traceback.rstrip(), err=True)
    from msflow.api import raise_for_failures

    raise_for_failures(result.states, str(result.session.pipeline.path))


def _warn(message: str) -> None:
    """``warning: message`` on stderr, yellow on a terminal."""
    line = f"warning: {message}"
    echo(f"\033[33m{line}\033[0m" if sys.stderr.isatty() else line, err=True)


def _echo_warnings(warnings: dict[str, list[str]], states: dict[str, str]) -> None:
    """Stage warnings; those of reused results say so (they were raised when computed)."""
    for stage, messages in warnings.items():
        origin = " (cached result)" if states.get(stage) == StageStatus.CACHED else ""
        for message in messages:
            _warn(f"{stage}{origin}: {message}")


def _echo_summary(
    patterns: tuple[str, ...], stages: dict[str, dict[str, object]], published: list[str], written: list[str]
) -> None:
    """The files published (``written`` by this run, or up to date) and the pipeline's ``summary:`` metrics on
    stdout (the run's result; progress and warnings go to stderr)."""
    from msflow.summary import published_lines, summary_lines

    lines, problems = summary_lines(list(patterns), stages)
    for problem in problems:
        _warn(problem)
    for line in published_lines(published, written) + lines:
        echo(line)


# ---------------------------------------------------------------------------------------------------------- status / why
@app.command()
def status(
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    overrides: Optional[List[str]] = typer.Option(None, "-S", "--set", help="stage.param=value override"),
) -> None:
    """What a run would do now, and why."""
    from msflow.inspect import dry_run
    from msflow.session import open_session

    session = open_session(pipeline_file(file, file_option), tuple(overrides or ()))
    dry = dry_run(session)
    session.save_memo()
    width = max(len(n) for n in dry)
    for name, d in dry.items():
        label = {DryStatus.CACHED: "cached", DryStatus.RUN: "will run", DryStatus.BLOCKED: "waits"}[d.state]
        echo(f"{name:<{width}}  {label}")
        for reason in d.reasons:
            echo(f"{'':<{width}}    - {reason}")
    counts = {state: sum(1 for d in dry.values() if d.state is state) for state in DryStatus}
    summary = f"{counts[DryStatus.CACHED]} cached, {counts[DryStatus.RUN]} to run"
    if counts[DryStatus.BLOCKED]:
        summary += f", {counts[DryStatus.BLOCKED]} waiting on them (rerun only if their inputs change)"
    echo(summary)


@app.command()
def why(
    stage: str = typer.Argument(..., help="stage name"),
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    overrides: Optional[List[str]] = typer.Option(None, "-S", "--set", help="stage.param=value override"),
) -> None:
    """Which part of STAGE's cache key changed since its last run (code file, param, input)."""
    from msflow.inspect import RunHistory, dry_run
    from msflow.session import open_session
    from msflow.spec import unknown_stage

    file = pipeline_file(file, file_option)
    session = open_session(file, tuple(overrides or ()))
    if stage not in session.pipeline.stages:
        raise UserError(unknown_stage(stage, session.pipeline.stages), file=str(file), field="STAGE")
    history = RunHistory(session)
    d = dry_run(session, history)[stage]
    previous = history.last(stage)
    session.save_memo()
    if d.state is DryStatus.CACHED:
        echo(f"{stage}: up to date (key {(d.key or '')[:12]})")
        return
    since = f" since run {previous['run']}" if previous else ""
    echo(f"{stage}: {'would run' if d.state is DryStatus.RUN else 'waits for upstream'}{since}")
    for reason in d.reasons:
        echo(f"  - {reason}")


# ---------------------------------------------------------------------------------------------------------- dag
@app.command()
def dag(
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    mermaid: bool = typer.Option(False, "--mermaid"),
    dot: bool = typer.Option(False, "--dot"),
) -> None:
    """Print the stage graph (text, Mermaid or Graphviz dot)."""
    from msflow.dag import render_dot, render_mermaid, render_text
    from msflow.spec import load_pipeline

    pipeline = load_pipeline(pipeline_file(file, file_option))
    echo(render_mermaid(pipeline) if mermaid else render_dot(pipeline) if dot else render_text(pipeline))


# ---------------------------------------------------------------------------------------------------------- show / export
@app.command()
def show(
    target: str = typer.Argument(..., help="STAGE or STAGE.output"),
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    overrides: Optional[List[str]] = typer.Option(None, "-S", "--set", help="stage.param=value override"),
) -> None:
    """Shapes, dtypes, statistics, metadata and metrics of a stage's artifact."""
    import json

    from msflow.inspect import resolve_artifact_key
    from msflow.session import open_session

    stage, _, output = target.partition(".")
    session = open_session(pipeline_file(file, file_option), tuple(overrides or ()))
    key, origin = resolve_artifact_key(session, stage)
    view = session.store.open(key)
    session.save_memo()
    echo(f"{stage}  {session.plans[stage].uses}\nkey {key}  ({origin})")
    if "cpu_seconds" in view.manifest:
        echo(f"computed in {view.manifest['compute_seconds']:.3g} s ({view.manifest['cpu_seconds']:.3g} s CPU)")
    parts = view.manifest.get("parts")
    if parts:  # msflow.parts: what it was built from, and how much of it an earlier run had computed
        echo(f"built from {_count(len(parts['keys']), 'part')}, {len(parts['reused'])} found stored when it ran")
    names = [output] if output else list(view.names)
    if output and output not in view:
        raise UserError(
            f"stage '{stage}' has no output '{output}'; outputs: {', '.join(view.names)}", field="STAGE.output"
        )
    for name in names:
        echo("  " + describe_array(name, view))
    if output:
        suffix = view.manifest["outputs"][output].get("file_suffix")
        if suffix:  # its bytes printed as numbers say nothing
            echo(f"a {suffix} file: msflow export {stage}.{output} FILE{suffix} writes it")
            return
        import numpy as np

        with np.printoptions(threshold=200, edgeitems=3, precision=5, suppress=True):
            echo(str(view[output]))
        return
    if view.warnings:
        echo("warnings:")
        for message in view.warnings:
            echo(f"  {message}")
    if view.metrics:
        echo("metrics:")
        for k, v in view.metrics.items():
            echo(f"  {k} = {v:.6g}" if isinstance(v, float) else f"  {k} = {v}")
    if view.meta:
        text = json.dumps(view.meta, indent=1)
        echo("meta:\n" + (text if len(text) < 4000 else text[:4000] + "\n  ... (truncated)"))


def describe_array(name: str, view: ArtifactView) -> str:
    import numpy as np

    entry = view.manifest["outputs"][name]
    if entry.get("file_suffix"):
        return f"{name:<18} file {entry['file_suffix']}  {entry['shape'][0]:,} bytes"
    arr = view[name]
    text = f"{name:<18} {entry['dtype']:<8} {tuple(entry['shape'])}"
    if arr.size and arr.dtype.kind in "fiub":
        vals = arr.astype(np.float64)
        finite = np.isfinite(vals)
        if finite.any():
            v = vals[finite]
            text += f"  min {v.min():.4g} max {v.max():.4g} mean {v.mean():.4g} std {v.std():.4g}"
        if (~finite).any():
            text += f"  non-finite {int((~finite).sum())}"
    return text


@app.command()
def export(
    target: str = typer.Argument(
        ..., help="STAGE.output, or STAGE: its only output, or all its outputs into a .npz file"
    ),
    dest: Path = typer.Argument(..., help="file to write: .npy, .npz, .csv, .json, or a file output's own suffix"),
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    overrides: Optional[List[str]] = typer.Option(None, "-S", "--set", help="stage.param=value override"),
) -> None:
    """Write an output to a file: .npy, .npz, .csv, .json, or a file output's own bytes (GLB, MP4, ...). STAGE
    alone writes the stage's only output, or every output of a stage of several into one .npz."""
    from msflow.exporting import export_output, export_outputs
    from msflow.inspect import resolve_artifact_key
    from msflow.session import open_session

    stage, _, output = target.partition(".")
    session = open_session(pipeline_file(file, file_option), tuple(overrides or ()))
    key, origin = resolve_artifact_key(session, stage)
    view = session.store.open(key)
    if output:
        export_output(view, output, dest)
        written = [output]
    else:
        written = export_outputs(view, stage, dest)
    session.save_memo()
    what = f"{stage}.{written[0]}" if len(written) == 1 else f"the {len(written)} outputs of {stage}"
    echo(f"wrote {dest} ({what}, {origin})", err=True)


# ---------------------------------------------------------------------------------------------------------- gc / verify
@app.command()
def gc(
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    keep_runs: int = typer.Option(10, "--keep-runs", help="runs whose artifacts stay"),
    dry_run: bool = typer.Option(False, "--dry-run", help="only list what would go"),
) -> None:
    """Drop artifacts that none of the most recent runs references; clear leftovers of killed runs and the damaged
    artifacts runs set aside."""
    from msflow.gc import collect_garbage
    from msflow.spec import load_pipeline

    report = collect_garbage(
        load_pipeline(pipeline_file(file, file_option)).open_store(),
        keep_runs=keep_runs,
        dry_run=dry_run,
    )
    remove, keep = ("would remove", "would keep") if dry_run else ("removed", "kept")
    parts = [
        f"{remove} {_count(len(report['artifacts']), 'artifact')} ({_size(report['bytes'])}{'' if dry_run else ' freed'})",
        f"{keep} {_count(report['kept'], 'artifact')}",
    ]
    if not dry_run:  # a dry run clears nothing and does not look for them
        parts.append(f"cleared {_count(len(report['tmp']), 'temporary directory', 'temporary directories')}")
    if report["damaged"]:
        parts.append(
            f"{remove} {_count(len(report['damaged']), 'damaged artifact')} set aside ({_size(report['damaged_bytes'])})"
        )
    echo(", ".join(parts))


def _size(n: int) -> str:
    """Bytes as people read them: ``512 B``, ``12.3 kB``, ``4.5 MB``, ``1.2 GB`` (powers of 1000, as disks count)."""
    for unit, scale in (("GB", 10**9), ("MB", 10**6), ("kB", 10**3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def _count(n: int, noun: str, plural: str | None = None) -> str:
    """``1 artifact``, ``2 artifacts``."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


@app.command()
def verify(
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    delete: bool = typer.Option(False, "--delete", help="remove corrupt artifacts"),
) -> None:
    """Recompute every artifact's content hashes and list the corrupt ones: exit 1 if there are any, unless
    --delete removed them all (exit 0: a run that needs one computes it again)."""
    from msflow.spec import load_pipeline

    store = load_pipeline(pipeline_file(file, file_option)).open_store()
    total, corrupt = _find_corrupt(store)
    if not corrupt:
        echo(f"verified {_count(total, 'artifact')}: 0 corrupt")
        return
    found = f"verified {_count(total, 'artifact')}: {len(corrupt)} corrupt"
    if not delete:
        it = "it" if len(corrupt) == 1 else "them"
        echo(f"{found}; `msflow verify --delete` removes {it} ({_recomputed(len(corrupt))})")
        raise typer.Exit(1)
    kept = _remove_corrupt(store, corrupt)
    removed = [key[:12] for key in corrupt if key not in kept]
    count = "" if not kept else f" {len(removed)}"  # "3 corrupt, removed" or "3 corrupt, 2 removed"
    echo(f"{found},{count} removed ({', '.join(removed)}); {_recomputed(len(removed))}" if removed else found)
    if kept:
        echo(f"error: {_count(len(kept), 'corrupt artifact')} could not be removed", err=True)
        raise typer.Exit(1)


def _recomputed(count: int) -> str:
    """What becomes of removed artifacts: only a run that needs one computes it (an old run's may never be)."""
    return f"a run that needs {'it computes it' if count == 1 else 'one computes it'} again"


def _find_corrupt(store: Store) -> tuple[int, list[str]]:
    """How many artifacts the store holds, and the keys of the corrupt ones (each listed with its problems)."""
    total, corrupt = 0, []
    for key in store.keys():
        total += 1
        problems = store.verify(key)
        if problems:
            corrupt.append(key)
            echo(f"corrupt {key}: " + "; ".join(problems))
    return total, corrupt


def _remove_corrupt(store: Store, keys: list[str]) -> list[str]:
    """Remove the artifacts ``keys`` (under their locks, as gc does: a run may be waiting on one); the keys that
    could not be removed, each said with why."""
    failed = []
    for key in keys:
        try:
            with store.lock(key):
                store.remove(key)
        except OSError as exc:
            echo(f"error: cannot remove {key}: {exc.strerror or exc}", err=True)
            failed.append(key)
    return failed


# ---------------------------------------------------------------------------------------------------------- sweeps, runs
@app.command()
def sweep(
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
    values: Optional[List[str]] = typer.Option(
        None, "-S", "--set", help="stage.param=v1,v2,... (comma lists form a grid)"
    ),
    grid: Optional[Path] = typer.Option(None, "--grid", help="grid file: grid / zip / variants"),
    jobs: int = typer.Option(1, "-j", "--jobs", help="stages to run at once across variants"),
    executor: str = typer.Option("local", "--executor", help="local or dask"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler tcp://host:port"),
    connect_timeout: float = typer.Option(10.0, "--connect-timeout", help="seconds to reach the scheduler"),
    fmt: str = typer.Option("table", "--format", help="table, md, csv or json"),
    sort: Optional[str] = typer.Option(None, "--sort", help="column to sort by (-column: descending)"),
    metrics: Optional[str] = typer.Option(
        None, "--metrics", help="stage.metric patterns, comma separated [default: the pipeline's summary:]"
    ),
    quiet: bool = typer.Option(False, "-q", "--quiet"),
) -> None:
    """Run a grid of parameter variants; print variant parameters against stage metrics."""
    from msflow.progress import SweepReporter
    from msflow.sweep import check_format, expand_variants, run_sweep

    check_format(fmt)  # before anything runs, not when the table is written
    variants = expand_variants(list(values or ()), grid)
    # the pipeline is loaded once per variant, with its overrides: a default `vars:` entry (a folder of takes
    # that only exists elsewhere) is never read on its own
    reporter = None if quiet else SweepReporter(len(variants))
    result = run_sweep(
        pipeline_file(file, file_option),
        variants,
        jobs=jobs,
        executor=executor,
        scheduler=scheduler,
        connect_timeout=connect_timeout,
        reporter=reporter,
        sort=sort,  # checked before any variant runs, its metric when the stage first finishes
    )
    if _echo_sweep(result, metrics, sort, fmt):
        raise typer.Exit(1)


def _echo_sweep(result: SweepResult, metrics: str | None, sort: str | None, fmt: str) -> int:
    """The results table on stdout (in the ``table`` format, each failed variant's whole error below it) and the
    sweep's summary on stderr; returns the number of failed variants."""
    from msflow.sweep import failure_lines, format_table, metric_columns, results_rows

    # columns: --metrics, else the pipeline's summary:, else the metrics that vary
    patterns = list(_split([metrics])) if metrics else result.summary or None
    header, rows = results_rows(result, metric_columns(result, patterns), sort)
    echo(format_table(header, rows, fmt))
    failures = failure_lines(result) if fmt == "table" else []  # the other formats keep errors whole
    if failures:
        echo()
        for line in failures:
            echo(line)
    failed = sum(1 for v in result.variants if not v.ok)
    echo(
        f"sweep {result.sweep_id}: {len(result.variants)} variants, {result.executed} stage executions for "
        f"{result.unique_keys} distinct keys, {failed} failed, {result.seconds:.2f}s",
        err=True,
    )
    return failed


@app.command()
def runs(
    file: Optional[Path] = typer.Argument(
        None,
        help="only the runs of this pipeline file (or -f FILE)",
        show_default="every run in pipeline.yaml's store",
    ),
    file_option: Optional[Path] = FILE_OPT,
    limit: int = typer.Option(20, "--limit", "-n", help="newest N runs"),
) -> None:
    """List runs (newest last): id, outcome, time, pipeline file, stage counts, sweep, variant or overrides."""
    from msflow.spec import load_pipeline

    file = given_pipeline_file(file, file_option)
    pipeline = load_pipeline(file or DEFAULT_FILE)
    only = pipeline.rel_path if file is not None else None
    listed = _newest_runs(pipeline.open_store(), only, limit)
    width = max((len(str(record.get("pipeline", "?"))) for _, record in listed), default=0)
    for run_id, record in listed:
        if "unreadable" in record:  # one damaged record does not hide the others
            echo(f"{run_id}  UNREADABLE  {record['unreadable']}")
            continue
        counts = ", ".join(f"{v} {k}" for k, v in record.get("counts", {}).items() if v)
        label = record.get("variant") or record.get("overrides") or ""
        sweep = f" sweep {record['sweep']}" if record.get("sweep") else ""
        source = "" if only else f"{record.get('pipeline', '?'):<{width}}  "  # "?": a record that names none
        echo(
            f"{run_id}  {_outcome(record):<7}  {record.get('seconds', 0):7.2f}s  "
            f"{source}{counts}{sweep}  {json.dumps(label) if label else ''}"
        )
    if not listed:
        echo(f"no runs of {only} yet" if only else "no runs yet")


def _outcome(record: dict[str, Any]) -> str:
    """A run's outcome as ``msflow runs`` shows it: ok, FAILED, or STOPPED (interrupted: Ctrl-C, SIGTERM)."""
    return "ok" if record.get("ok") else "STOPPED" if record.get("interrupted") else "FAILED"


def _newest_runs(store: Store, pipeline: str | None, limit: int) -> list[tuple[str, dict[str, Any]]]:
    """The newest ``limit`` run records (oldest first), only those of ``pipeline`` (its path relative to the project)
    when given; an unreadable record stands as {"unreadable": why}, whichever pipeline it was of."""
    from msflow.errors import CorruptRecord

    found: list[tuple[str, dict[str, Any]]] = []
    for run_id in reversed(store.run_ids()):
        if len(found) >= limit:
            break
        try:
            record = store.read_run(run_id)
        except CorruptRecord as exc:
            found.append((run_id, {"unreadable": str(exc)}))
            continue
        if pipeline is None or record.get("pipeline") == pipeline:
            found.append((run_id, record))
    return found[::-1]


@app.command()
def compare(
    run_a: str = typer.Argument(..., help="run id (or unique prefix/suffix)"),
    run_b: str = typer.Argument(..., help="run id (or unique prefix/suffix)"),
    file: Optional[Path] = FILE_ARG,
    file_option: Optional[Path] = FILE_OPT,
) -> None:
    """Differences between two runs: params and cache keys exactly, metrics within a relative tolerance of 1e-9
    (absolute 1e-12), numbers to 6 significant digits with the change."""
    from msflow.comparing import compare_runs
    from msflow.spec import load_pipeline

    store = load_pipeline(pipeline_file(file, file_option)).open_store()
    for line in compare_runs(store.read_run(run_a), store.read_run(run_b)):
        echo(line)


# ---------------------------------------------------------------------------------------------------------- report
@app.command()
def report(
    run: Optional[str] = typer.Argument(
        None, help="run or sweep id (default: the newest run); a .yaml/.yml file alone is FILE"
    ),
    file: Optional[Path] = FILE_ARG,
    out: Path = typer.Option(Path("report.html"), "-o", "--out", help="HTML file to write"),
    file_option: Optional[Path] = FILE_OPT,
    jobs: int = typer.Option(2, "-j", "--jobs", help="processes rendering figures"),
    metric: Optional[str] = typer.Option(None, "--metric", help="sweeps: stage.metric to plot"),
) -> None:
    """Write one self-contained HTML page of a run (graph, params, keys, metrics, figures) or of a sweep."""
    from msflow.report import build_report

    if file is None and run is not None and run.lower().endswith((".yaml", ".yml")):
        file, run = Path(run), None  # `msflow report pipelines/capture.yaml`: no run id ends so
    summary = build_report(pipeline_file(file, file_option), out, run, jobs=jobs, metric=metric)
    echo(
        f"wrote {summary['path']} ({summary['bytes'] / 1e6:.1f} MB, {summary['figures']} figures, "
        f"{summary['rendered']} rendered) in {summary['seconds']:.2f}s",
        err=True,
    )
    for failure in summary["failed"]:
        echo(f"figure failed: {failure}", err=True)
