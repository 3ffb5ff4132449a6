"""Scheduling a resolved pipeline: cache keys from content, cache hits, execution, early cutoff, run records.

A stage's key is computed when its upstream stages are settled, from the content hashes of the outputs it reads.
So a stage that reruns but produces identical content leaves its dependents' keys unchanged: early cutoff needs no
special case. Keys never contain paths or times.
"""

from __future__ import annotations

import json
import uuid
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from datetime import UTC
from typing import Any

from msflow.errors import UserError
from msflow.hashing import FileHashMemo, json_hash
from msflow.plan import StagePlan
from msflow.spec import FilesRef, Pipeline, rel_to, topological_order

KEY_SCHEME = 2  # 2: artifact format 2 (streamed array hashes, chunk checksums)
DONE = ("cached", "ran")


@dataclass
class StageState:
    name: str
    state: str = "pending"  # pending, cached, running, ran, failed, skipped
    key: str | None = None
    parts: dict | None = None
    manifest: dict | None = None
    seconds: float = 0.0
    error: str | None = None
    user_error: dict | None = None
    traceback: str | None = None
    inputs: dict = field(default_factory=dict)
    detail: str = ""


def select_stages(pipeline: Pipeline, until: str | None) -> list[str]:
    order = topological_order(pipeline.stages)
    if until is None:
        return order
    if until not in pipeline.stages:
        from msflow.spec import _suggest

        raise UserError(
            f"--until: unknown stage '{until}'{_suggest(until, pipeline.stages)}",
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
    pipeline: Pipeline, name: str, states: dict[str, StageState], file_memo: FileHashMemo, interface: dict
) -> tuple[dict, dict, dict]:
    """(key part, job spec, provenance) of a stage's inputs; upstream stages must be settled."""
    parts: dict[str, Any] = {}
    job: dict[str, Any] = {}
    provenance: dict[str, Any] = {}
    node = pipeline.stages[name]
    for input_name, decl in interface["inputs"].items():
        ref = node.inputs.get(input_name)
        if ref is None:
            parts[input_name] = job[input_name] = None
            continue
        if isinstance(ref, FilesRef):
            hashes = {}
            for label, path in ref.files:
                try:
                    hashes[label] = file_memo.hash(path)
                except OSError as exc:
                    raise UserError(
                        f"cannot read data file: {exc}",
                        file=str(pipeline.path),
                        stage=name,
                        field=f"inputs.{input_name}.{label}",
                    ) from None
            parts[input_name] = {"files": hashes}
            job[input_name] = {"kind": "files", "files": [list(f) for f in ref.files]}
            fields = ref.fields_by_label()
            if fields:  # only when some label has fields: keys of plain file inputs stay as they were
                parts[input_name]["fields"] = job[input_name]["fields"] = fields
            provenance[input_name] = {
                "files": {label: rel_to(path, pipeline.root) for label, path in ref.files},
                "hashes": hashes,
            }
            continue
        upstream = states[ref.stage]
        manifest = upstream.manifest or {}
        if ref.output is None:
            digest = manifest["content_hash"]
            job[input_name] = {"kind": "artifact", "key": upstream.key}
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
            job[input_name] = {
                "kind": "array",
                "key": upstream.key,
                "output": ref.output,
                "lazy": bool(decl.get("lazy")),
            }
        parts[input_name] = {"hash": digest}
        provenance[input_name] = {"from": ref.describe(), "hash": digest}
    return parts, job, provenance


def resource_hashes(plan: StagePlan, root, file_memo: FileHashMemo) -> dict:
    """Content hashes of the data files a stage's code reads by default (Stage.resources)."""
    return {name: file_memo.hash(root / path) for name, path in plan.interface.get("resources", {}).items()}


def key_parts(plan: StagePlan, inputs: dict, resources: dict | None = None) -> dict:
    parts = {"scheme": KEY_SCHEME, "class": plan.uses, "code": plan.code, "params": plan.params, "inputs": inputs}
    if resources:
        parts["resources"] = resources
    return parts


def stage_key(
    pipeline: Pipeline, plan: StagePlan, name: str, states: dict[str, StageState], file_memo: FileHashMemo
) -> tuple[dict, str, dict, dict]:
    """(key parts, key, job inputs, input provenance) of a stage whose upstream stages are settled."""
    inputs, job_inputs, provenance = input_parts(pipeline, name, states, file_memo, plan.interface)
    parts = key_parts(plan, inputs, resource_hashes(plan, pipeline.root, file_memo))
    return parts, json_hash(parts), job_inputs, provenance


class Runner:
    """Runs the selected stages of a resolved pipeline on an executor, reporting state changes."""

    def __init__(
        self,
        pipeline: Pipeline,
        plans: dict[str, StagePlan],
        store,
        memo: dict,
        *,
        executor,
        until: str | None = None,
        force: tuple[str, ...] = (),
        reporter=None,
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
            raise UserError(f"--force: unknown stage(s) {unknown}", file=str(pipeline.path), field="--force")
        self.force = set(force)
        self.reporter = reporter
        self.jobs = jobs  # the run's worker count, handed to each stage (Stage.jobs); not part of any key
        self.states = {name: StageState(name) for name in self.selected}
        self.waiting: list[str] = []
        self.file_memo = FileHashMemo(memo.setdefault("data", {}))

    def _report(self, state: StageState) -> None:
        if self.reporter is not None:
            self.reporter.update(state)

    def prepare(self, name: str) -> dict | None:
        """Compute the key; return a job when the stage must run, None when it is cached."""
        state = self.states[name]
        plan = self.plans[name]
        state.parts, state.key, job_inputs, state.inputs = stage_key(
            self.pipeline, plan, name, self.states, self.file_memo
        )
        if name not in self.force and self.store.has(state.key):
            state.manifest = self.store.manifest(state.key)
            state.state = "cached"
            self._report(state)
            return None
        state.state = "running"
        self._report(state)
        return {
            "store": self.store.url,
            "store_options": self.store.options,
            "project_root": str(self.pipeline.root),
            "key": state.key,
            "stage": name,
            "uses": plan.uses,
            "params": plan.params,
            "inputs": job_inputs,
            "force": name in self.force,
            "jobs": self.jobs,
            "key_parts": state.parts,
        }

    def settle(self, name: str, outcome: dict) -> None:
        state = self.states[name]
        state.seconds = outcome.get("seconds", 0.0)
        if outcome["state"] in DONE:
            state.manifest = outcome["manifest"]
            state.state = outcome["state"]
            if outcome.get("concurrent"):
                state.detail = "computed by a concurrent run"
            elif outcome["state"] == "cached" and not state.detail:
                state.detail = "computed meanwhile"
        else:
            state.state = "failed"
            state.error = outcome.get("error")
            state.user_error = outcome.get("user_error")
            state.traceback = outcome.get("traceback")
        self._report(state)

    def ready(self) -> list[str]:
        """Stages whose upstream is settled, removed from the waiting list; marks skips on upstream failure."""
        out = []
        for name in list(self.waiting):
            dep_states = [self.states[d].state for d in self.pipeline.stages[name].deps]
            if any(s in ("failed", "skipped") for s in dep_states):
                self.waiting.remove(name)
                self.states[name].state = "skipped"
                self.states[name].detail = "an upstream stage failed"
                self._report(self.states[name])
                out.append(None)
            elif all(s in DONE for s in dep_states):
                self.waiting.remove(name)
                out.append(name)
        return out

    def run(self) -> dict[str, StageState]:
        schedule([self], self.executor)
        return self.states


def schedule(runners: list[Runner], executor) -> None:
    """Advance several runners (one per sweep variant) on one executor until all stages are settled.

    A key needed by several runners at the same time is submitted once; the others wait for it and count it as
    cached ("shared"). Across processes and machines the per-key store lock gives the same guarantee.
    """
    for runner in runners:
        runner.waiting = list(runner.selected)
    inflight: dict[str, list[tuple[Runner, str]]] = {}
    running: dict[Future, str] = {}

    def settle(key: str, outcome: dict) -> None:
        waiters = inflight.pop(key)
        first_runner, first_name = waiters[0]
        first_runner.settle(first_name, outcome)
        for runner, name in waiters[1:]:
            shared = dict(outcome)
            if shared["state"] == "ran":
                shared["state"] = "cached"
                shared["concurrent"] = False
                runner.states[name].detail = f"computed once for several variants ({first_name})"
            runner.settle(name, shared)

    while any(r.waiting for r in runners) or running:
        progressed = True
        while progressed:
            progressed = False
            for runner in runners:
                for name in runner.ready():
                    progressed = True
                    if name is None:
                        continue
                    try:
                        job = runner.prepare(name)
                    except UserError as exc:
                        runner.settle(
                            name,
                            {"state": "failed", "user_error": exc.located(stage=name).to_json(), "error": str(exc)},
                        )
                        continue
                    if job is None:
                        continue
                    key = job["key"]
                    if key in inflight:
                        inflight[key].append((runner, name))
                        continue
                    inflight[key] = [(runner, name)]
                    future = executor.submit(json.dumps(job, allow_nan=False))
                    if future.done():
                        settle(key, _outcome(future))
                    else:
                        running[future] = key
        if running:
            finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for future in finished:
                settle(running.pop(future), _outcome(future))


def _outcome(future: Future) -> dict:
    try:
        return json.loads(future.result())
    except Exception as exc:  # a worker process died (SIGKILL, OOM) or the executor broke
        return {"state": "failed", "error": f"worker lost: {type(exc).__name__}: {exc}"}


def new_run_id() -> str:
    """Sortable by start time to the microsecond (records of one second must still order newest last)."""
    from datetime import datetime

    return datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%f") + "-" + uuid.uuid4().hex[:6]
