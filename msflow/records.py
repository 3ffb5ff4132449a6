"""Run records (one JSON per run in the store) and ``pipeline.lock`` (diffable YAML beside the pipeline file)."""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

from msflow.atomic import write_atomic
from msflow.hashing import json_hash
from msflow.jobs import StageStatus
from msflow.plan import StagePlan
from msflow.runner import StageState
from msflow.spec import LOCK_MARK, Pipeline, lock_file

LOCK_HEADER = (
    LOCK_MARK + " after each run of {name}; the state of every stage's last\n"
    "# successful execution (cache key, params, input and output content hashes). Commit it; do not edit.\n"
)


def stage_record(plan: StagePlan, state: StageState) -> dict[str, Any]:
    manifest = state.manifest or {}
    return {
        "uses": plan.uses,
        "state": state.state.value,
        "detail": state.detail or None,
        "key": state.key,
        "key_parts": state.parts,
        "inputs": state.inputs,
        "outputs": {k: v["hash"] for k, v in manifest.get("outputs", {}).items()},
        "shapes": {k: v["shape"] for k, v in manifest.get("outputs", {}).items()},
        "content_hash": manifest.get("content_hash"),
        "metrics": manifest.get("metrics", {}),
        "warnings": manifest.get("warnings", []),
        "seconds": round(state.seconds, 6),
        "compute_seconds": round(state.compute_seconds, 6),
        "cpu_seconds": round(state.cpu_seconds, 6),
        "worker": state.worker,
        "attempts": state.attempts,
        "error": state.error,
        "user_error": state.user_error,
        "traceback": state.traceback,
    }


def build_record(
    run_id: str,
    pipeline: Pipeline,
    plans: dict[str, StagePlan],
    states: dict[str, StageState],
    *,
    started: float,
    finished: float,
    executor: str,
    jobs: int,
    argv: list[str] | None = None,
    label: dict[str, Any] | None = None,
) -> dict[str, Any]:
    dists: dict[str, str] = {}
    for plan in plans.values():
        dists.update(plan.code["dists"])
    from msflow.version import __version__

    return {
        "id": run_id,
        "pipeline": pipeline.rel_path,
        "project": pipeline.root.name,
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started)),
        "seconds": round(finished - started, 6),
        "ok": all(s.state.done for s in states.values()),
        "executor": executor,
        "jobs": jobs,
        "argv": argv or [],
        "overrides": list(pipeline.overrides),
        "variant": label or {},
        "config": {
            name: {
                "uses": node.uses,
                "params": plans[name].params,
                "inputs": {k: v.describe() for k, v in node.inputs.items()},
            }
            for name, node in pipeline.stages.items()
        },
        "stages": {name: stage_record(plans[name], state) for name, state in states.items()},
        "counts": {
            s.value: sum(1 for st in states.values() if st.state is s)
            for s in (StageStatus.CACHED, StageStatus.RAN, StageStatus.FAILED, StageStatus.SKIPPED)
        },
        "versions": {"msflow": __version__, "python": platform.python_version(), **dists},
        "platform": {
            "system": platform.system(),
            "release": platform.release(),
            "machine": platform.machine(),
            "python": sys.implementation.name,
            "cpus": os.cpu_count(),
        },
    }


#: the fields of a run record that a small (no-op) record carries itself; the rest come from its ``same_as``
SMALL_FIELDS = ("id", "pipeline", "started", "seconds", "ok", "executor", "jobs", "argv", "overrides", "variant")


def record_digest(record: dict[str, Any]) -> str:
    """What two runs must share for one's record to stand for the other's: configuration, keys, outputs, versions."""
    stages = {n: [s.get("key"), s.get("content_hash"), s.get("warnings")] for n, s in record["stages"].items()}
    stable = {k: record.get(k) for k in ("pipeline", "config", "versions", "overrides", "variant", "sweep")}
    return json_hash({**stable, "stages": stages})


def small_record(record: dict[str, Any], same_as: str) -> dict[str, Any]:
    """The record of a pure no-op: when, how, and the run whose full record describes the same state."""
    small = {k: record[k] for k in SMALL_FIELDS if k in record}
    small.update({"same_as": same_as, "counts": record["counts"]})
    if "sweep" in record:
        small["sweep"] = record["sweep"]
    return small


def lock_entries(pipeline: Pipeline, plans: dict[str, StagePlan], states: dict[str, StageState]) -> dict[str, Any]:
    entries = {}
    for name, state in states.items():
        if not state.state.done:
            continue
        manifest = state.manifest or {}
        entries[name] = {
            "uses": plans[name].uses,
            "key": state.key,
            "code": plans[name].code_digest,
            "params": plans[name].params,
            "inputs": {
                k: (v.get("hash") if "hash" in v and "files" not in v else v.get("hashes"))
                for k, v in state.inputs.items()
            },
            "outputs": {k: v["hash"] for k, v in sorted(manifest.get("outputs", {}).items())},
        }
    return entries


def lock_path(pipeline: Pipeline) -> Path:
    return lock_file(pipeline.path)


def read_lock(pipeline: Pipeline) -> dict[str, Any]:
    import yaml

    try:
        loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
        data = yaml.load(lock_path(pipeline).read_text(encoding="utf-8"), Loader=loader)
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError, yaml.YAMLError):
        return {}


def update_lock(pipeline: Pipeline, plans: dict[str, StagePlan], states: dict[str, StageState]) -> bool:
    """Merge this run's settled stages into pipeline.lock; drop stages no longer in the pipeline. True if written."""
    import yaml

    previous = read_lock(pipeline)
    stages = {k: v for k, v in (previous.get("stages") or {}).items() if k in pipeline.stages}
    stages.update(lock_entries(pipeline, plans, states))
    data = {"version": 1, "pipeline": pipeline.path.name, "stages": dict(sorted(stages.items()))}
    try:
        if json_hash(data) == json_hash({k: previous.get(k) for k in data}):
            return False
    except (TypeError, ValueError):  # a hand-edited lock with non-JSON values: rewrite it
        pass
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    text = LOCK_HEADER.format(name=pipeline.path.name) + yaml.dump(data, Dumper=dumper, sort_keys=True, width=120)
    write_atomic(lock_path(pipeline), text)
    return True
