"""Running pipelines: ``msflow.run`` (one pipeline) and ``run_sessions`` (several at once: sweeps), ``RunResult``."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msflow.errors import CorruptArtifact, StageFailed, UserError
from msflow.jobs import StageStatus
from msflow.runner import Reporter, Runner, StageState, StopRun
from msflow.session import Session, open_session
from msflow.stores.base import new_run_id

if TYPE_CHECKING:
    from collections.abc import Callable

    from msflow.artifact import ArtifactView
    from msflow.executors import LazyExecutor
    from msflow.publishers import Publication
    from msflow.shipping import CodeTree


@dataclass
class RunResult:
    """What a run did: per-stage states, the run record, and access to every artifact as numpy."""

    session: Session
    states: dict[str, StageState]
    record: dict[str, Any]
    #: the files the pipeline's ``publish:`` entries hold after the run (absolute paths; written by it or already
    #: up to date), and the warnings publishing gave (a file another pipeline or entry had published, replaced)
    published: list[str] = field(default_factory=list)
    publish_warnings: list[str] = field(default_factory=list)
    #: those of ``published`` this run wrote; the others already held the same output and were not touched
    newly_published: list[str] = field(default_factory=list)

    def __repr__(self) -> str:
        counts = ", ".join(f"{v} {k}" for k, v in self.record.get("counts", {}).items() if v)
        return f"RunResult(run {self.run_id}, {'ok' if self.ok else 'FAILED'}: {counts or 'nothing selected'})"

    @property
    def ok(self) -> bool:
        return bool(self.record["ok"])

    @property
    def run_id(self) -> str:
        return str(self.record["id"])

    @property
    def warnings(self) -> dict[str, list[str]]:
        """Stage -> the warnings its artifact carries (stages that ran or were reused)."""
        return {
            n: list((s.manifest or {}).get("warnings", []))
            for n, s in self.states.items()
            if (s.manifest or {}).get("warnings")
        }

    @property
    def executed(self) -> list[str]:
        return [n for n, s in self.states.items() if s.state is StageStatus.RAN]

    @property
    def summary(self) -> dict[str, Any]:
        """The pipeline's ``summary:`` metrics of this run, ``{"stage.metric": value}`` (what ``msflow run``
        prints last; msflow.summary)."""
        from msflow.summary import summary_entries

        return dict(summary_entries(list(self.session.pipeline.summary), self.record["stages"])[0])

    @property
    def metrics(self) -> dict[str, dict[str, Any]]:
        return {n: (s.manifest or {}).get("metrics", {}) for n, s in self.states.items()}

    def key(self, stage: str) -> str:
        state = self.states.get(stage)
        if state is None or state.key is None:
            raise KeyError(f"stage '{stage}' was not part of this run")
        return state.key

    def artifact(self, stage: str) -> ArtifactView:
        return self.session.store.open(self.key(stage))

    def load(self, ref: str) -> Any:
        """``"stage.output"`` -> numpy array."""
        stage, _, output = ref.partition(".")
        return self.artifact(stage)[output]


@dataclass
class Execution:
    """One session's part of a run of several sessions: its runner states and its run record."""

    session: Session
    states: dict[str, StageState]
    record: dict[str, Any]
    seen: dict[str, str] = field(default_factory=dict)  #: stat signatures of the data files and folders read


def run_sessions(
    sessions: list[Session],
    *,
    jobs: int = 1,
    executor: str = "local",
    scheduler: str | None = None,
    connect_timeout: float = 10.0,
    until: str | None = None,
    force: tuple[str, ...] = (),
    reporters: list[Reporter | None] | None = None,
    labels: list[dict[str, Any]] | None = None,
    argv: list[str] | None = None,
    extra: dict[str, Any] | None = None,
) -> list[Execution]:
    """Run resolved sessions together on one executor and write one run record each: the one execution path of
    ``msflow run`` (one session) and ``msflow sweep`` (one per variant). Work shared by sessions (same key)
    is done once. ``labels`` are the sessions' variant parameters; ``extra`` goes into every record."""
    from msflow.executors import make_executor
    from msflow.runner import schedule
    from msflow.stores.base import RUN_PID_VARIABLE
    from msflow.worker import pin_blas_threads

    os.environ[RUN_PID_VARIABLE] = str(os.getpid())  # inherited by the workers: locks they take name this run
    # msflow gc fails while a run holds this (it would delete what runs make); a run waits for a gc in progress
    with sessions[0].store.in_use(on_wait=report_gc_wait):
        started = time.time()
        pin_blas_threads()
        pool = make_executor(
            executor,
            jobs,
            scheduler,
            connect_timeout,
            on_start=sessions[0].store.clean_tmp,
            code_trees=code_trees_of(sessions),
            batch=len(sessions) > 1,
        )
        runners = _runners_for(sessions, pool, jobs=jobs, until=until, force=force, reporters=reporters)
        settings: dict[str, Any] = dict(started=started, jobs=jobs, force=force, labels=labels, argv=argv)
        interrupted = False
        try:
            schedule(runners, pool)
        except KeyboardInterrupt:  # Ctrl-C (or SIGTERM, msflow.cli): stop the stages running, don't wait for them
            interrupted = True
            raise
        except StopRun as stop:  # a reporter found a user error: stopped as by Ctrl-C, then reported as the error
            interrupted = True
            raise stop.error from None
        finally:
            pool.shutdown(abort=interrupted)
            if interrupted:
                with contextlib.suppress(Exception):  # nothing may hide the interrupt
                    sessions[0].store.clean_tmp()  # what the stopped jobs were writing (their processes are gone)
                with contextlib.suppress(Exception):  # what finished, for msflow runs, why and gc's keep list
                    _record_executions(
                        sessions, runners, pool.name, extra=dict(extra or {}, interrupted=True), **settings
                    )
        executions = _record_executions(sessions, runners, pool.name, extra=extra, **settings)
        for session in {id(s.memo): s for s in sessions}.values():  # sessions may share one memo
            session.save_memo()
        return executions


def _runners_for(
    sessions: list[Session],
    pool: LazyExecutor,
    *,
    jobs: int,
    until: str | None,
    force: tuple[str, ...],
    reporters: list[Reporter | None] | None,
) -> list[Runner]:
    """One runner per session, all on the one executor."""
    return [
        Runner(
            session.pipeline,
            session.plans,
            session.store,
            session.memo,
            executor=pool,
            until=until,
            force=force,
            reporter=(reporters or [None] * len(sessions))[index],
            jobs=jobs,
        )
        for index, session in enumerate(sessions)
    ]


def _record_executions(
    sessions: list[Session],
    runners: list[Runner],
    executor: str,
    *,
    labels: list[dict[str, Any]] | None,
    **settings: Any,
) -> list[Execution]:
    """Write the run record of each session (``_record_execution``): what it computed, also when the run was
    interrupted (``extra`` then says so: ``msflow runs`` shows it stopped, gc keeps what it finished)."""
    return [
        _record_execution(session, runner, executor=executor, label=labels[index] if labels else None, **settings)
        for index, (session, runner) in enumerate(zip(sessions, runners))
    ]


def _record_execution(
    session: Session,
    runner: Runner,
    *,
    started: float,
    executor: str,
    jobs: int,
    force: tuple[str, ...],
    label: dict[str, Any] | None,
    argv: list[str] | None,
    extra: dict[str, Any] | None,
) -> Execution:
    """Build and write the run record of one session's part of the run."""
    from msflow.records import build_record

    record = build_record(
        new_run_id(),
        session.pipeline,
        session.plans,
        runner.states,
        started=started,
        finished=time.time(),
        executor=executor,
        jobs=jobs,
        argv=argv,
        label=label,
    )
    record.update(extra or {})
    if runner.repairs:
        record["repairs"] = runner.repairs
    write_record(session, record, noop=not runner.repairs and not force)
    return Execution(session, runner.states, record, runner.file_memo.seen)


def code_trees_of(sessions: list[Session]) -> Callable[[str], CodeTree]:
    """Project root -> the code its sessions' stages need (``msflow.shipping``), computed when first asked."""
    from functools import cache

    @cache
    def tree(root: str) -> CodeTree:
        from msflow.shipping import code_tree

        mine = [s for s in sessions if str(s.pipeline.root) == root]
        plans = [plan for s in mine for plan in s.plans.values()]
        return code_tree(Path(root), plans, mine[0].memo.setdefault("code", {}) if mine else None)

    return tree


def write_record(session: Session, record: dict[str, Any], noop: bool) -> None:
    """Write a run record. A pure no-op (everything cached) whose stages, keys and outputs equal those of a full
    record already written only gets a small record pointing at it (``same_as``): no-ops do not grow the store by a
    full copy each. Readers see the full record either way (``Store.read_run`` expands it)."""
    from msflow.records import record_digest, small_record

    digest = record_digest(record)
    known = session.memo.setdefault("records", {})
    all_cached = all(s["state"] == StageStatus.CACHED and not s.get("detail") for s in record["stages"].values())
    if noop and all_cached and digest in known:
        session.store.write_run(small_record(record, known[digest]))
        return
    session.store.write_run(record)
    known[digest] = record["id"]


def run(
    path: str | Path,
    overrides: Sequence[str] = (),
    *,
    jobs: int = 1,
    until: str | None = None,
    force: Sequence[str] = (),
    executor: str = "local",
    scheduler: str | None = None,
    reporter: Reporter | None = None,
    argv: list[str] | None = None,
    raise_on_failure: bool = True,
    label: dict[str, Any] | None = None,
    session: Session | None = None,
    connect_timeout: float = 10.0,
    publish_dir: str | Path | None = None,
) -> RunResult:
    """Run a pipeline (``msflow.run``, documented there with an example); the CLI's ``run`` too."""
    session = session or open_session(path, overrides, publish_dir=publish_dir)
    options: dict[str, Any] = dict(
        jobs=jobs,
        executor=executor,
        scheduler=scheduler,
        connect_timeout=connect_timeout,
        until=until,
        force=tuple(force),
        reporters=[reporter],
        labels=[label] if label else None,
        argv=argv,
    )
    (execution,) = run_sessions([session], **options)
    try:
        publication = finish_run(execution)
    except CorruptArtifact as exc:  # an artifact to publish failed its integrity check: recompute, publish again
        where = session.store.quarantine(exc.key or "", f"publishing: {exc.problem}")
        repair = {"stage": exc.stage or "", "key": exc.key or "", "problem": exc.problem, "moved_to": where}
        (execution,) = run_sessions([session], **options)
        execution.record.setdefault("repairs", []).insert(0, repair)
        publication = finish_run(execution)
    if not until and not force and publish_dir is None and not execution.record.get("repairs"):
        save_fast_state(execution, publication.files)  # what the next no-op `msflow run` answers from
    result = RunResult(
        session, execution.states, execution.record, publication.files, publication.warnings, publication.written
    )
    if raise_on_failure:
        raise_for_failures(execution.states, str(session.pipeline.path))
    return result


def report_gc_wait(holder: dict[str, Any]) -> None:
    """Tell the user why a run has not started: ``msflow gc`` is deleting from the store."""
    from msflow.stores.base import describe_holder

    who = f" ({describe_holder(holder)})" if holder else ""
    print(f"msflow: msflow gc{who} is cleaning the store; waiting for it to finish", file=sys.stderr, flush=True)


def finish_run(execution: Execution) -> Publication:
    """What a plain run does after its stages settle: update pipeline.lock and publish."""
    from msflow.publishers import Publication
    from msflow.records import update_lock

    session = execution.session
    update_lock(session.pipeline, session.plans, execution.states)
    if not session.pipeline.publish:
        return Publication()
    from msflow.exporting import publish_outputs

    publication = publish_outputs(session, execution.states)
    session.save_memo()
    return publication


def save_fast_state(execution: Execution, published: list[str]) -> None:
    """After a run where every stage is done on a local store, save what a no-op answer depends on (see
    msflow.fastpath): signatures of the pipeline, lock, code, data, artifacts and published files."""
    from msflow.fastpath import save_state, signature
    from msflow.records import lock_path
    from msflow.stores.local import LocalStore

    session = execution.session
    store, pipeline = session.store, session.pipeline
    if not isinstance(store, LocalStore) or not all(s.state.done for s in execution.states.values()):
        return
    watch = watched_code(session)
    if watch is None or any(ref.listed is None for ref in pipeline.files_refs()):
        return
    watch.update(execution.seen)
    watch[str(pipeline.path)] = pipeline.source_signature
    watch[str(lock_path(pipeline))] = signature(str(lock_path(pipeline)))
    for ref in pipeline.files_refs():
        watch.update({folder: signature(folder) for folder in ref.listed or ()})
    for state in execution.states.values():
        assert state.key is not None
        folder = store.artifact_path(state.key)
        watch[str(folder)] = signature(str(folder))
        watch[str(folder / "zarr.json")] = signature(str(folder / "zarr.json"))
    for dest in pipeline.publish.values():
        watch[dest] = signature(dest)
    known = session.memo.get("records", {})
    from msflow.records import record_digest
    from msflow.summary import summary_lines

    same_as = known.get(record_digest(execution.record), execution.record["id"])
    save_state(
        str(pipeline.path),
        list(pipeline.overrides),
        str(pipeline.root),
        watch,
        list(execution.states),
        {
            n: list((s.manifest or {}).get("warnings", []))
            for n, s in execution.states.items()
            if (s.manifest or {}).get("warnings")
        },
        same_as,
        str(store.root / "runs"),
        pipeline.rel_path,
        summary_lines(list(pipeline.summary), execution.record["stages"]),
        published,
        list(pipeline.warnings),
    )


def watched_code(session: Session) -> dict[str, str] | None:
    """Signatures of the files and folders of every stage's import closure, as recorded when the closure was
    computed (None when a closure is not memoised: then the state is not saved)."""
    from msflow.fastpath import listing

    closures = session.memo.get("code", {}).get("closures", {})
    root = session.pipeline.root
    watch: dict[str, str] = {}
    for plan in session.plans.values():
        if not plan.code["modules"]:
            continue  # an installed stage module: versioned (the environment digest covers it)
        hit = closures.get(plan.uses.partition(":")[0])
        if not hit:
            return None
        for path, sig in zip(hit["files"], hit["sig"]):
            full = path if os.path.isabs(path) else str(root / path)
            watch[full] = listing(full) if os.path.isdir(full) else sig
    return watch


def raise_for_failures(states: dict[str, StageState], pipeline_file: str | None = None) -> None:
    """Raise the first crash (StageFailed), else the first user error, of a run's stages (one a stage raised
    about its params names no file: it is the pipeline's, ``pipeline_file``)."""
    failed = [s for s in states.values() if s.state is StageStatus.FAILED]
    crashes = [s for s in failed if not s.user_error]
    if crashes:
        first = crashes[0]
        raise StageFailed(first.name, first.error or "failed", first.traceback or "")
    if failed:
        ue = failed[0].user_error or {}
        file = ue.get("file") or pipeline_file
        raise UserError(ue["message"], file=file, stage=ue.get("stage"), field=ue.get("field"))
