"""Running pipelines: ``msflow.run`` (one pipeline) and ``run_sessions`` (several at once: sweeps), ``RunResult``."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msflow.errors import StageFailed, UserError
from msflow.jobs import StageStatus
from msflow.runner import Reporter, Runner, StageState, new_run_id
from msflow.session import Session, open_session

if TYPE_CHECKING:
    from collections.abc import Callable

    from msflow.artifact import ArtifactView
    from msflow.shipping import CodeTree


@dataclass
class RunResult:
    """What a run did: per-stage states, the run record, and access to every artifact as numpy."""

    session: Session
    states: dict[str, StageState]
    record: dict[str, Any]

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
    pool = make_executor(
        executor,
        jobs,
        scheduler,
        connect_timeout,
        on_start=sessions[0].store.clean_tmp,
        code_trees=code_trees_of(sessions),
    )
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


def code_trees_of(sessions: list[Session]) -> Callable[[str], CodeTree]:
    """Project root -> the code its sessions' stages need (``msflow.shipping``), computed when first asked."""
    from functools import cache

    @cache
    def tree(root: str) -> CodeTree:
        from msflow.shipping import code_tree

        plans = [plan for s in sessions if str(s.pipeline.root) == root for plan in s.plans.values()]
        return code_tree(Path(root), plans)

    return tree


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
