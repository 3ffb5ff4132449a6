"""Python API: ``msflow.run(path, overrides=...)`` and the helpers the CLI shares with it."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msflow.errors import StageFailed, UserError
from msflow.hashing import json_hash
from msflow.plan import StagePlan, resolve
from msflow.runner import Runner, StageState, new_run_id
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


def run(
    path: str | Path,
    overrides=(),
    *,
    jobs: int = 1,
    until: str | None = None,
    force=(),
    executor: str = "local",
    scheduler: str | None = None,
    reporter=None,
    argv: list[str] | None = None,
    raise_on_failure: bool = True,
    label: dict | None = None,
    session: Session | None = None,
    connect_timeout: float = 10.0,
) -> RunResult:
    """Run a pipeline. Raises UserError for mistakes in the pipeline (nothing is written), and after the run
    StageFailed (a stage crashed) or UserError (a stage rejected its data) unless ``raise_on_failure`` is False."""
    from msflow.executors import make_executor
    from msflow.records import build_record, update_lock
    from msflow.worker import pin_blas_threads

    started = time.time()
    session = session or open_session(path, overrides)
    pin_blas_threads()
    pool = make_executor(executor, jobs, scheduler, connect_timeout, on_start=session.store.clean_tmp)
    runner = Runner(
        session.pipeline,
        session.plans,
        session.store,
        session.memo,
        executor=pool,
        until=until,
        force=tuple(force),
        reporter=reporter,
        jobs=jobs,
    )
    try:
        states = runner.run()
    finally:
        pool.shutdown()
    record = build_record(
        new_run_id(),
        session.pipeline,
        session.plans,
        states,
        started=started,
        finished=time.time(),
        executor=pool.name,
        jobs=jobs,
        argv=argv,
        label=label,
    )
    session.store.write_run(record)
    update_lock(session.pipeline, session.plans, states)
    if session.pipeline.publish:
        from msflow.exporting import publish_outputs

        publish_outputs(session, states)
    session.save_memo()
    result = RunResult(session, states, record)
    if raise_on_failure:
        raise_for_failures(states)
    return result


def raise_for_failures(states: dict[str, StageState]) -> None:
    failed = [s for s in states.values() if s.state == "failed"]
    crashes = [s for s in failed if not s.user_error]
    if crashes:
        first = crashes[0]
        raise StageFailed(first.name, first.error or "failed", first.traceback or "")
    if failed:
        ue = failed[0].user_error
        raise UserError(ue["message"], file=ue.get("file"), stage=ue.get("stage"), field=ue.get("field"))
