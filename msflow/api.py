"""Python API: ``msflow.run(path, overrides=...)`` and the helpers the CLI shares with it."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msflow.errors import StageFailed, UserError
from msflow.hashing import json_hash
from msflow.jobs import StageStatus
from msflow.plan import StagePlan, resolve
from msflow.runner import Reporter, Runner, StageState, new_run_id
from msflow.spec import Pipeline, load_pipeline

MEMO_ENTRIES = 2000  # per memo section; an evicted entry is only recomputed (one parse, import or file hash)


def trim_memo(memo: dict) -> None:
    """Keep each growing memo section to its newest entries: every code edit adds fingerprints, interfaces and
    params that later runs never ask for again, and the memo is read by every no-op run."""
    sections = [memo.get("interfaces"), memo.get("params"), memo.get("data"), memo.get("published")]
    code = memo.get("code") or {}
    sections += [code.get("files"), code.get("closures")]
    for section in sections:
        if isinstance(section, dict) and len(section) > MEMO_ENTRIES:
            for key in list(section)[: len(section) - MEMO_ENTRIES]:
                del section[key]


@dataclass
class Session:
    """A loaded, resolved pipeline with its store and memo: what every command starts from."""

    pipeline: Pipeline
    store: Any
    memo: dict
    plans: dict[str, StagePlan]
    memo_digest: str

    def save_memo(self) -> None:
        trim_memo(self.memo)
        digest = json_hash(self.memo)
        if digest != self.memo_digest:
            try:
                self.store.save_memo(self.memo)
            except OSError:
                pass  # a read-only store still runs; it only loses the memo
            self.memo_digest = digest


def open_session(path: str | Path, overrides=(), memo: dict | None = None) -> Session:
    """Load and resolve a pipeline; ``memo`` shares one memo between sessions (sweep variants)."""
    pipeline = load_pipeline(path, tuple(overrides))
    store = pipeline.open_store()
    memo = store.load_memo() if memo is None else memo
    digest = json_hash(memo)
    plans = resolve(pipeline, memo)
    return Session(pipeline, store, memo, plans, digest)


@dataclass
class RunResult:
    """What a run did: per-stage states, the run record, and access to every artifact as numpy."""

    session: Session
    states: dict[str, StageState]
    record: dict

    @property
    def ok(self) -> bool:
        return self.record["ok"]

    @property
    def run_id(self) -> str:
        return self.record["id"]

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
        return [n for n, s in self.states.items() if s.state == "ran"]

    @property
    def metrics(self) -> dict[str, dict]:
        return {n: (s.manifest or {}).get("metrics", {}) for n, s in self.states.items()}

    def key(self, stage: str) -> str:
        state = self.states.get(stage)
        if state is None or state.key is None:
            raise KeyError(f"stage '{stage}' was not part of this run")
        return state.key

    def artifact(self, stage: str):
        return self.session.store.open(self.key(stage))

    def load(self, ref: str):
        """``"stage.output"`` -> numpy array."""
        stage, _, output = ref.partition(".")
        return self.artifact(stage)[output]


@dataclass
class Execution:
    """One session's part of a run of several sessions: its runner states and its run record."""

    session: Session
    states: dict[str, StageState]
    record: dict[str, Any]


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
    from msflow.records import build_record
    from msflow.runner import schedule
    from msflow.worker import pin_blas_threads

    started = time.time()
    pin_blas_threads()
    pool = make_executor(executor, jobs, scheduler, connect_timeout, on_start=sessions[0].store.clean_tmp)
    runners = [
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
    try:
        schedule(runners, pool)
    finally:
        pool.shutdown()
    executions = []
    for index, (session, runner) in enumerate(zip(sessions, runners)):
        label = labels[index] if labels else None
        record = build_record(
            new_run_id(),
            session.pipeline,
            session.plans,
            runner.states,
            started=started,
            finished=time.time(),
            executor=pool.name,
            jobs=jobs,
            argv=argv,
            label=label,
        )
        record.update(extra or {})
        session.store.write_run(record)
        executions.append(Execution(session, runner.states, record))
    for session in {id(s.memo): s for s in sessions}.values():  # sessions may share one memo
        session.save_memo()
    return executions


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
) -> RunResult:
    """Run a pipeline (``msflow.run``, documented there with an example); the CLI's ``run`` too."""
    session = session or open_session(path, overrides)
    (execution,) = run_sessions(
        [session],
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
    finish_run(execution)
    result = RunResult(session, execution.states, execution.record)
    if raise_on_failure:
        raise_for_failures(execution.states)
    return result


def finish_run(execution: Execution) -> None:
    """What a plain run does after its stages settle: update pipeline.lock and publish."""
    from msflow.records import update_lock

    session = execution.session
    update_lock(session.pipeline, session.plans, execution.states)
    if session.pipeline.publish:
        from msflow.exporting import publish_outputs

        publish_outputs(session, execution.states)
        session.save_memo()


def raise_for_failures(states: dict[str, StageState]) -> None:
    """Raise the first crash (StageFailed), else the first user error, of a run's stages."""
    failed = [s for s in states.values() if s.state is StageStatus.FAILED]
    crashes = [s for s in failed if not s.user_error]
    if crashes:
        first = crashes[0]
        raise StageFailed(first.name, first.error or "failed", first.traceback or "")
    if failed:
        ue = failed[0].user_error or {}
        raise UserError(ue["message"], file=ue.get("file"), stage=ue.get("stage"), field=ue.get("field"))
