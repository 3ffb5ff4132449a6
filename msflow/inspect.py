"""What would run and why: dry key computation against the store and comparison with the last run's key parts."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from msflow.errors import CorruptArtifact, UserError
from msflow.hashing import FileHashMemo
from msflow.jobs import DryStatus, StageStatus
from msflow.runner import StageState, key_parts, stage_key
from msflow.session import Session
from msflow.spec import topological_order


@dataclass
class DryState:
    name: str
    state: DryStatus
    key: str | None = None
    parts: dict[str, Any] | None = None
    reasons: list[str] = field(default_factory=list)
    manifest: dict[str, Any] | None = None
    corrupt: CorruptArtifact | None = None  #: its artifact exists but failed its integrity check


class RunHistory:
    """This pipeline's run records, newest first, each read at most once (records can be large)."""

    def __init__(self, session: Session):
        self.session = session
        self._pending = list(reversed(session.store.run_ids()))
        self._read: list[tuple[str, dict[str, Any]]] = []

    def _records(self) -> Iterator[tuple[str, dict[str, Any]]]:
        yield from self._read
        while self._pending:
            run_id = self._pending.pop(0)
            try:
                record = self.session.store.read_run(run_id)
            except (UserError, OSError, ValueError):
                continue
            if record.get("pipeline") == self.session.pipeline.rel_path:
                self._read.append((run_id, record))
                yield run_id, record

    def last(self, stage: str) -> dict[str, Any] | None:
        """The newest settled (cached or ran) entry of ``stage``, with its run id."""
        for run_id, record in self._records():
            entry = record.get("stages", {}).get(stage)
            if entry and entry.get("key_parts") and entry["state"] in (StageStatus.CACHED, StageStatus.RAN):
                return {**entry, "run": run_id}
        return None


def dry_run(session: Session, history: RunHistory | None = None) -> dict[str, DryState]:
    """Keys of every stage whose upstream artifacts exist; reasons for each stage that would run."""
    pipeline, store = session.pipeline, session.store
    history = history or RunHistory(session)
    states: dict[str, StageState] = {}
    dry: dict[str, DryState] = {}
    memo = FileHashMemo(session.memo.setdefault("data", {}))
    for name in topological_order(pipeline.stages):
        blocked = [d for d in pipeline.stages[name].deps if dry[d].state is not DryStatus.CACHED]
        plan = session.plans[name]
        if blocked:
            reasons = [f"upstream {', '.join(blocked)} must run first; this stage reruns if their outputs change"]
            previous = history.last(name)
            if previous:
                reasons += [
                    r
                    for r in explain(previous["key_parts"], {**key_parts(plan, {}), "inputs": None})
                    if not r.startswith("input")
                ]
            dry[name] = DryState(name, DryStatus.BLOCKED, reasons=reasons)
            states[name] = StageState(name)
            continue
        full, key, _, provenance = stage_key(pipeline, plan, name, states, memo)
        state = StageState(name, key=key, parts=full, inputs=provenance)
        corrupt = None
        if store.has(key):
            try:
                state.state, state.manifest = StageStatus.CACHED, store.manifest(key)
            except CorruptArtifact as exc:
                corrupt = exc.located(stage=name)
        if state.state is StageStatus.CACHED:
            dry[name] = DryState(name, DryStatus.CACHED, key, full, manifest=state.manifest)
        elif corrupt is not None:
            reason = f"its artifact is corrupt ({corrupt.problem}): a run moves it aside and recomputes it"
            state.state = StageStatus.PENDING
            dry[name] = DryState(name, DryStatus.RUN, key, full, [reason], corrupt=corrupt)
        else:
            previous = history.last(name)
            if previous is None:
                reasons = ["never run (no earlier run record of this stage)"]
            else:
                reasons = explain(previous["key_parts"], full, provenance) or [
                    "key unchanged since the last run but its artifact is missing from the store "
                    "(garbage-collected, or a different store)"
                ]
            dry[name] = DryState(name, DryStatus.RUN, key, full, [*being_computed(store.computing(key)), *reasons])
        states[name] = state
    return dry


def being_computed(holder: dict[str, Any] | None) -> list[str]:
    """The reason line for a stage another run is computing now (``Store.computing``), or none."""
    if holder is None:
        return []
    since = holder.get("since")
    age = f", for {time.time() - since:.0f} s" if isinstance(since, (int, float)) else ""
    from msflow.stores.base import describe_holder

    return [f"being computed now by a run in progress ({describe_holder(holder)}{age}); a run started now waits for it"]


def explain(old: dict[str, Any], new: dict[str, Any], provenance: dict[str, Any] | None = None) -> list[str]:
    """Human-readable differences between two key-part dicts (code files, versions, params, inputs)."""
    reasons: list[str] = []
    if old.get("scheme") != new.get("scheme"):
        reasons.append("msflow's key scheme changed")
    if old.get("class") != new.get("class"):
        reasons.append(f"class changed: {old.get('class')} -> {new.get('class')}")
    old_code, new_code = old.get("code") or {}, new.get("code") or {}
    old_mods, new_mods = old_code.get("modules", {}), new_code.get("modules", {})
    for path in sorted(set(old_mods) | set(new_mods)):
        if path not in old_mods:
            reasons.append(f"code: {path} is newly imported")
        elif path not in new_mods:
            reasons.append(f"code: {path} is no longer imported")
        elif old_mods[path] != new_mods[path]:
            reasons.append(f"code: {path} changed")
    old_d, new_d = old_code.get("dists", {}), new_code.get("dists", {})
    for dist in sorted(set(old_d) | set(new_d)):
        if old_d.get(dist) != new_d.get(dist):
            reasons.append(f"package {dist}: {old_d.get(dist, 'not used')} -> {new_d.get(dist, 'not used')}")
    if old_code.get("python") != new_code.get("python"):
        reasons.append(f"python {old_code.get('python')} -> {new_code.get('python')}")
    reasons += [f"param {p}" for p in _diff_values(old.get("params") or {}, new.get("params") or {})]
    old_r, new_r = old.get("resources") or {}, new.get("resources") or {}
    reasons += [
        f"data file of the stage's code changed: resource {r}"
        for r in sorted(set(old_r) | set(new_r))
        if old_r.get(r) != new_r.get(r) and new.get("inputs") is not None
    ]
    if new.get("inputs") is not None:
        old_in, new_in = old.get("inputs") or {}, new.get("inputs") or {}
        for name in sorted(set(old_in) | set(new_in)):
            a, b = old_in.get(name), new_in.get(name)
            if a == b:
                continue
            source = (provenance or {}).get(name, {})
            if isinstance(b, dict) and "files" in b and isinstance(a, dict) and "files" in a:
                changed = sorted(k for k in set(a["files"]) | set(b["files"]) if a["files"].get(k) != b["files"].get(k))
                paths = source.get("files", {})
                if changed:
                    reasons.append(
                        f"input {name}: data file content changed: {', '.join(paths.get(k, k) for k in changed)}"
                    )
                relabelled = sorted(
                    k
                    for k in set(a.get("fields", {})) | set(b.get("fields", {}))
                    if a.get("fields", {}).get(k) != b.get("fields", {}).get(k)
                )
                if relabelled:
                    reasons.append(f"input {name}: fields of {', '.join(relabelled)} changed")
            else:
                origin = f" (from {source['from']})" if source.get("from") else ""
                reasons.append(f"input {name}: content changed{origin}")
    return reasons


def _diff_values(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k, "<unset>"), new.get(k, "<unset>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += _diff_values(a, b, f"{prefix}{k}.")
        elif a != b:
            out.append(f"{prefix}{k}: {a!r} -> {b!r}")
    return out


def resolve_artifact_key(session: Session, stage: str) -> tuple[str, str]:
    """Key of the artifact ``show``/``export`` should use: the current one if present, else the last run's."""
    if stage not in session.pipeline.stages:
        from msflow.spec import unknown_stage

        raise UserError(
            unknown_stage(stage, session.pipeline.stages),
            file=str(session.pipeline.path),
            field="STAGE",
        )
    history = RunHistory(session)
    dry = dry_run(session, history)
    key = dry[stage].key
    corrupt = dry[stage].corrupt
    if corrupt is not None:
        raise corrupt
    if dry[stage].state is DryStatus.CACHED and key is not None:
        return key, "current"
    previous = history.last(stage)
    if previous and session.store.has(previous["key"]):
        return previous["key"], f"from run {previous['run']} (stale: the pipeline changed since)"
    raise UserError(
        f"stage '{stage}' has no artifact in the store yet: run the pipeline first "
        f"(msflow run {session.pipeline.path.name} --until {stage})",
        file=str(session.pipeline.path),
        stage=stage,
    )
