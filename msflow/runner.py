"""Scheduling a resolved pipeline: cache keys from content, cache hits, execution, early cutoff, run records.

A stage's key is computed when its upstream stages are settled, from the content hashes of the outputs it reads.
So a stage that reruns but produces identical content leaves its dependents' keys unchanged: early cutoff needs no
special case. Keys never contain paths or times.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from msflow.errors import CorruptArtifact, UserError
from msflow.executors import Executor
from msflow.hashing import FileHashMemo, json_hash
from msflow.jobs import Job, JobInput, Outcome, StageStatus
from msflow.plan import StagePlan
from msflow.spec import FilesRef, Pipeline, rel_to, topological_order, unknown_stage
from msflow.stores.base import Store
from msflow.version import KEY_SCHEME  # defined in a leaf module: workers check it too


class Reporter(Protocol):
    """Receives every state change of a stage (the progress display). ``update`` may raise ``StopRun`` to stop
    the run."""

    def update(self, state: StageState) -> None: ...


class StopRun(Exception):
    """Raised by a reporter to stop the run at once over a user error it found in a stage's result (msflow sweep:
    its ``--sort`` names a metric the stage does not give). ``msflow.api.run_sessions`` stops the stages running,
    records what finished as stopped, and raises ``error``. Not a ``UserError`` itself: the scheduler turns those
    into a failed stage, and this is no failure of the stage."""

    def __init__(self, error: UserError):
        super().__init__(str(error))
        self.error = error


@dataclass
class StageState:
    name: str
    state: StageStatus = StageStatus.PENDING
    key: str | None = None
    parts: dict[str, Any] | None = None
    manifest: dict[str, Any] | None = None
    seconds: float = 0.0
    error: str | None = None
    user_error: dict[str, Any] | None = None
    traceback: str | None = None
    inputs: dict[str, Any] = field(default_factory=dict)
    detail: str = ""
    worker: str | None = None  #: where it ran (a Dask worker's address, or "<host> pid <pid>")
    attempts: int = 0  #: executions started (0: none; more than 1: retried after its worker died)
    compute_seconds: float = 0.0  #: time in the stage's own ``run``
    cpu_seconds: float = 0.0  #: CPU time of the worker process in ``run``
    checked: bool = True  #: the runner asked the store for the key before submitting (``Runner.needs_check``)

    def __repr__(self) -> str:
        key = f", key={self.key[:12]}" if self.key else ""
        return f"StageState({self.name!r}, {self.state.value}{key})"


def select_stages(pipeline: Pipeline, until: str | None) -> list[str]:
    """The stages a run covers, in topological order: all, or ``until`` and what it needs."""
    order = topological_order(pipeline.stages)
    if until is None:
        return order
    if until not in pipeline.stages:
        raise UserError(
            unknown_stage(until, pipeline.stages),
            file=str(pipeline.path),
            field="--until",
        )
    needed: set[str] = set()
    stack = [until]
    while stack:
        name = stack.pop()
        if name not in needed:
            needed.add(name)
            stack.extend(pipeline.stages[name].deps)
    return [n for n in order if n in needed]


def input_parts(
    pipeline: Pipeline,
    name: str,
    states: dict[str, StageState],
    file_memo: FileHashMemo,
    interface: dict[str, Any],
) -> tuple[dict[str, Any], dict[str, JobInput | None], dict[str, Any]]:
    """(key part, job inputs, provenance) of a stage's inputs; upstream stages must be settled."""
    parts: dict[str, Any] = {}
    job: dict[str, JobInput | None] = {}
    provenance: dict[str, Any] = {}
    node = pipeline.stages[name]
    for input_name, decl in interface["inputs"].items():
        ref = node.inputs.get(input_name)
        if ref is None:
            parts[input_name] = job[input_name] = None
        elif isinstance(ref, FilesRef):
            parts[input_name], job[input_name], provenance[input_name] = files_part(
                pipeline, name, input_name, ref, file_memo
            )
        else:
            manifest = states[ref.stage].manifest or {}
            if ref.output is None:
                digest = manifest["content_hash"]
                job[input_name] = JobInput("artifact", key=states[ref.stage].key)
            else:
                entry = manifest["outputs"].get(ref.output)
                if entry is None:  # an optional output the upstream run did not produce
                    raise UserError(
                        f"stage '{ref.stage}' produced no output '{ref.output}' (it is optional)",
                        file=str(pipeline.path),
                        stage=name,
                        field=f"inputs.{input_name}",
                    )
                digest = entry["hash"]
                lazy = bool(decl.get("lazy"))
                job[input_name] = JobInput("array", key=states[ref.stage].key, output=ref.output, lazy=lazy)
            parts[input_name] = {"hash": digest}
            provenance[input_name] = {"from": ref.describe(), "hash": digest}
    return parts, job, provenance


def files_part(
    pipeline: Pipeline, name: str, input_name: str, ref: FilesRef, file_memo: FileHashMemo
) -> tuple[dict[str, Any], JobInput, dict[str, Any]]:
    """(key part, job input, provenance) of a data-files input: content hashes (memoised by stat) and fields."""
    hashes = {}
    for label, path in ref.files:
        try:
            hashes[label] = file_memo.hash(Path(path))
        except OSError as exc:
            raise UserError(
                f"cannot read data file: {exc}",
                file=str(pipeline.path),
                stage=name,
                field=f"inputs.{input_name}.{label}",
            ) from None
    part: dict[str, Any] = {"files": hashes}
    fields = ref.fields_by_label()
    if fields:  # only when some label has fields: keys of plain file inputs stay as they were
        part["fields"] = fields
    job = JobInput("files", files=tuple(ref.files), fields=fields or None)
    provenance = {"files": {label: rel_to(Path(path), pipeline.root) for label, path in ref.files}, "hashes": hashes}
    return part, job, provenance


def resource_hashes(plan: StagePlan, root: Path, file_memo: FileHashMemo) -> dict[str, str]:
    """Content hashes of the data files a stage's code reads by default (Stage.resources)."""
    return {name: file_memo.hash(root / path) for name, path in plan.interface.get("resources", {}).items()}


def key_parts(
    plan: StagePlan, inputs: dict[str, Any] | None, resources: dict[str, str] | None = None
) -> dict[str, Any]:
    """What a stage's cache key hashes: scheme, class, code, params, inputs (and resources when it has any)."""
    parts: dict[str, Any] = {
        "scheme": KEY_SCHEME,
        "class": plan.uses,
        "code": plan.code,
        "params": plan.params,
        "inputs": inputs,
    }
    if resources:
        parts["resources"] = resources
    return parts


def stage_key(
    pipeline: Pipeline, plan: StagePlan, name: str, states: dict[str, StageState], file_memo: FileHashMemo
) -> tuple[dict[str, Any], str, dict[str, JobInput | None], dict[str, Any]]:
    """(key parts, key, job inputs, input provenance) of a stage whose upstream stages are settled."""
    inputs, job_inputs, provenance = input_parts(pipeline, name, states, file_memo, plan.interface)
    parts = key_parts(plan, inputs, resource_hashes(plan, pipeline.root, file_memo))
    return parts, json_hash(parts), job_inputs, provenance


def parts_detail(manifest: dict[str, Any] | None) -> str:
    """'2 of 3 parts reused' for a stage that found some of its parts (msflow.parts) computed by earlier runs."""
    parts = (manifest or {}).get("parts") or {}
    reused, total = len(parts.get("reused", [])), len(parts.get("keys", {}))
    return f"{reused} of {total} parts reused" if reused else ""


class Runner:
    """Runs the selected stages of a resolved pipeline on an executor, reporting state changes.

    Scheduling is linear in the number of stages and edges: each stage counts its unsettled upstream stages, and
    settling a stage only visits its own dependents.
    """

    def __init__(
        self,
        pipeline: Pipeline,
        plans: dict[str, StagePlan],
        store: Store,
        memo: dict[str, Any],
        *,
        executor: Executor,
        until: str | None = None,
        force: tuple[str, ...] = (),
        reporter: Reporter | None = None,
        jobs: int = 1,
    ):
        self.pipeline = pipeline
        self.plans = plans
        self.store = store
        self.memo = memo
        self.executor = executor
        self.selected = select_stages(pipeline, until)
        unknown = [f for f in force if f not in pipeline.stages]
        if unknown:
            raise UserError(f"unknown stage(s) {unknown}", file=str(pipeline.path), field="--force")
        self.force = set(force)
        self.reporter = reporter
        self.jobs = jobs  # the run's worker count, handed to each stage (Stage.jobs); not part of any key
        self.states = {name: StageState(name) for name in self.selected}
        self.file_memo = FileHashMemo(memo.setdefault("data", {}))
        self.dependents: dict[str, list[str]] = {name: [] for name in self.selected}
        self.blocking: dict[str, int] = {}
        for name in self.selected:
            deps = pipeline.stages[name].deps
            self.blocking[name] = len(deps)
            for dep in deps:
                self.dependents[dep].append(name)
        self.queue = deque(name for name in self.selected if not self.blocking[name])
        self.unsettled = len(self.selected)
        self.repaired: set[str] = set()  # keys of corrupt artifacts moved aside (each repaired once)
        self.repairs: list[dict[str, str]] = []  # what was moved aside, for the record and the CLI

    def _report(self, state: StageState) -> None:
        if self.reporter is not None:
            self.reporter.update(state)

    @property
    def busy(self) -> bool:
        """Some selected stage is not settled yet."""
        return self.unsettled > 0

    def take_ready(self) -> list[str]:
        """Stages whose upstream stages are all done, in the order they became ready."""
        ready = list(self.queue)
        self.queue.clear()
        return ready

    def prepare(self, name: str) -> Job | None:
        """Compute the key; return a job when the stage must run, None when it is cached (and settled)."""
        state = self.states[name]
        plan = self.plans[name]
        state.parts, state.key, job_inputs, state.inputs = stage_key(
            self.pipeline, plan, name, self.states, self.file_memo
        )
        state.checked = self.needs_check(name)
        if state.checked and name not in self.force and self.store.has(state.key):
            try:
                state.manifest = self.store.manifest(state.key)
            except CorruptArtifact as exc:  # a damaged artifact is never used: move it aside, compute anew
                self._quarantine(name, state.key, exc.problem)
            else:
                self._finish(state, StageStatus.CACHED)
                return None
        state.state = StageStatus.RUNNING
        self._report(state)
        return Job(
            store=self.store.url,
            store_options=self.store.options,
            project_root=str(self.pipeline.root),
            key=state.key,
            stage=name,
            uses=plan.uses,
            params=plan.params,
            inputs=job_inputs,
            force=name in self.force,
            checked=state.checked,
            jobs=self.jobs,
            key_parts=state.parts,
            in_process=bool(plan.interface.get("in_process")),
            cheap=bool(plan.interface.get("cheap")),
        )

    def needs_check(self, name: str) -> bool:
        """Whether to ask the store for the stage's artifact before submitting it. Not on a remote store when an
        input was computed by this run: new content makes a new key (early cutoff aside), and the worker checks
        the store under the key's lock anyway, so asking here too would cost every executed stage one more round
        trip. A stage found there counts as cached, as here."""
        if not self.store.remote:
            return True
        return not any(self.states[dep].state is StageStatus.RAN for dep in self.pipeline.stages[name].deps)

    def settle(self, name: str, outcome: Outcome) -> None:
        """Record what became of a stage's job (or of its preparation) and release its dependents."""
        state = self.states[name]
        if outcome.corrupt and self._repair(name, outcome.corrupt["key"], outcome.corrupt["problem"]):
            return
        state.seconds = outcome.seconds
        state.worker, state.attempts = outcome.worker, outcome.attempts
        state.compute_seconds, state.cpu_seconds = outcome.compute_seconds, outcome.cpu_seconds
        if outcome.attempts > 1:
            state.detail = f"attempt {outcome.attempts}: {outcome.attempts - 1} worker(s) lost mid-stage"
        if outcome.status.done:
            state.manifest = outcome.manifest
            if outcome.status is StageStatus.RAN and not state.detail:
                state.detail = parts_detail(outcome.manifest)
            if outcome.concurrent:
                state.detail = "computed by a concurrent run"
            elif outcome.status is StageStatus.CACHED and not state.detail and state.checked:
                state.detail = "computed meanwhile"
        else:
            state.error = outcome.error
            state.user_error = outcome.user_error
            state.traceback = outcome.traceback
        self._finish(state, outcome.status if outcome.status.done else StageStatus.FAILED)

    def retrying(self, name: str, lost_worker: str, attempt: int) -> None:
        """The executor lost the worker running ``name`` and started attempt ``attempt`` elsewhere (its thread)."""
        state = self.states[name]
        state.detail = f"retrying (attempt {attempt}): worker {lost_worker} was lost"
        self._report(state)

    def _finish(self, state: StageState, status: StageStatus) -> None:
        state.state = status
        self.unsettled -= 1
        self._report(state)
        for child in self.dependents[state.name]:
            if not status.done:
                self._skip(child)
                continue
            self.blocking[child] -= 1
            if not self.blocking[child] and self.states[child].state is StageStatus.PENDING:
                self.queue.append(child)

    def _quarantine(self, stage: str, key: str, problem: str) -> None:
        where = self.store.quarantine(key, f"stage '{stage}': {problem}")
        self.repaired.add(key)
        self.repairs.append({"stage": stage, "key": key, "problem": problem, "moved_to": where})
        self.states[stage].detail = "recomputed: its artifact was corrupt"

    def _repair(self, name: str, key: str, problem: str) -> bool:
        """An input of ``name`` failed its integrity check: move the upstream artifact aside, recompute it, then
        run ``name`` again; or the stage's own artifact, found damaged by the worker that checked it instead of the
        runner: move it aside and run ``name`` again. False when the key is neither, or was repaired already (then
        ``name`` fails)."""
        state = self.states[name]
        if key == state.key and not state.checked:
            if key in self.repaired:
                return False
            self._quarantine(name, key, problem)
            self._requeue(state)
            return True
        upstream = [d for d in self.pipeline.stages[name].deps if self.states[d].key == key]
        if not upstream:
            return False
        if key not in self.repaired:
            for up in upstream:
                self._quarantine(up, key, problem)
                self._reopen(up)
        if self.states[upstream[0]].state.done:  # recomputed meanwhile: run again now
            self._requeue(state)
        else:
            state.state = StageStatus.PENDING
            self._report(state)
            self.blocking[name] += 1  # wait for the recomputed upstream artifact
        return True

    def _requeue(self, state: StageState) -> None:
        state.state = StageStatus.PENDING
        self._report(state)
        self.queue.append(state.name)

    def _reopen(self, name: str) -> None:
        """Make a settled stage pending again (its artifact is gone) and hold back its pending dependents."""
        state = self.states[name]
        state.state, state.manifest = StageStatus.PENDING, None
        self.unsettled += 1
        self.queue.append(name)
        self._report(state)
        for child in self.dependents[name]:
            if self.states[child].state is StageStatus.PENDING:
                self.blocking[child] += 1

    def _skip(self, name: str) -> None:
        state = self.states[name]
        if state.state is not StageStatus.PENDING:
            return
        state.detail = "an upstream stage failed"
        self._finish(state, StageStatus.SKIPPED)

    def run(self) -> dict[str, StageState]:
        schedule([self], self.executor)
        return self.states


def schedule(runners: list[Runner], executor: Executor) -> None:
    """Advance several runners (one per sweep variant) on one executor until all stages are settled.

    A key needed by several runners at the same time is submitted once; the others wait for it and count it as
    cached ("shared"). Across processes and machines the per-key store lock gives the same guarantee.
    """
    inflight: dict[str, list[tuple[Runner, str]]] = {}
    running: dict[Future[str], str] = {}

    def settle(key: str, outcome: Outcome) -> None:
        waiters = inflight.pop(key)
        first_runner, first_name = waiters[0]
        first_runner.settle(first_name, outcome)
        for runner, name in waiters[1:]:
            shared = Outcome(**{**vars(outcome)})
            if shared.status is StageStatus.RAN:
                shared.status = StageStatus.CACHED
                shared.concurrent = False
                runner.states[name].detail = f"computed once for several variants ({first_name})"
            runner.settle(name, shared)

    def submit(runner: Runner, name: str) -> None:
        try:
            job = runner.prepare(name)
        except UserError as exc:
            user_error = exc.located(stage=name).to_json()
            runner.settle(name, Outcome(StageStatus.FAILED, user_error=user_error, error=str(exc)))
            return
        if job is None:
            return
        if job.key in inflight:
            inflight[job.key].append((runner, name))
            return
        inflight[job.key] = [(runner, name)]
        future = executor.submit(
            job.to_json(),
            lambda lost, attempt: runner.retrying(name, lost, attempt),
        )
        if future.done():
            settle(job.key, outcome_of(future))
        else:
            running[future] = job.key

    while True:
        progressed = True
        while progressed:
            progressed = False
            for runner in runners:
                for name in runner.take_ready():
                    progressed = True
                    submit(runner, name)
        if not running:
            break
        finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
        for future in finished:
            settle(running.pop(future), outcome_of(future))


def outcome_of(future: Future[str]) -> Outcome:
    """The outcome a worker sent back, or a failure when the worker died (SIGKILL, OOM) or the executor broke."""
    try:
        return Outcome.from_json(future.result())
    except Exception as exc:
        return Outcome.crashed(f"worker lost: {type(exc).__name__}: {exc}")
