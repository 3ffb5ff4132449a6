"""The contract between the scheduler and the executors: a ``Job`` goes out, an ``Outcome`` comes back.

Both cross process and machine boundaries as JSON strings (``to_json``/``from_json``), so nothing but JSON ever
travels to a worker (a process pool, a Dask cluster). ``StageStatus`` is the state of one stage in a run;
``DryStatus`` what a dry run (``msflow status``) predicts.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any, Literal


class StageStatus(StrEnum):
    """The state of one stage in a run (a ``str``: records and displays hold the plain value)."""

    PENDING = "pending"  #: waiting for its upstream stages
    CACHED = "cached"  #: its artifact was already in the store (or computed by a concurrent run)
    RUNNING = "running"  #: submitted to an executor
    RAN = "ran"  #: computed by this run
    FAILED = "failed"  #: raised, returned an invalid result, or its worker died
    SKIPPED = "skipped"  #: an upstream stage failed

    @property
    def done(self) -> bool:
        """Settled with an artifact (cached or ran): dependents may run."""
        return self in (StageStatus.CACHED, StageStatus.RAN)

    @property
    def settled(self) -> bool:
        """Nothing more will happen to the stage in this run."""
        return self in (StageStatus.CACHED, StageStatus.RAN, StageStatus.FAILED, StageStatus.SKIPPED)


class DryStatus(StrEnum):
    """What ``msflow status`` predicts for a stage."""

    CACHED = "cached"  #: its key is in the store
    RUN = "run"  #: its key is known and missing: it will run
    BLOCKED = "blocked"  #: an upstream stage must run first; it reruns only if that changes its inputs


@dataclass(frozen=True)
class JobInput:
    """One input of a job: data files (labels, absolute paths, fields), a whole artifact, or one output."""

    kind: Literal["files", "artifact", "array"]
    key: str | None = None  #: artifact and array: the upstream artifact's key
    output: str | None = None  #: array: the output read
    lazy: bool = False  #: array: handed over as a lazy stored array (msflow.stored)
    #: files: (label, absolute path) pairs, in order; shipped jobs: (label, file name), the content in ``blobs``
    files: tuple[tuple[str, str], ...] = ()
    fields: dict[str, dict[str, str]] | None = None  #: files: label -> {field: value}
    #: shipped jobs (msflow.shipping): label -> content hash of the file (or folder tree) among the store's blobs
    blobs: dict[str, str] | None = None
    folders: tuple[str, ...] = ()  #: shipped jobs: labels whose blob is a folder's tree (``{"folder": {path: hash}}``)

    @classmethod
    def from_json(cls, value: dict[str, Any]) -> JobInput:
        files = tuple((str(a), str(b)) for a, b in value.get("files", ()))
        return cls(**{**value, "files": files, "folders": tuple(value.get("folders", ()))})


@dataclass(frozen=True)
class Job:
    """Everything a worker needs to compute one stage and publish its artifact."""

    store: str  #: store location (path or URL) ...
    store_options: dict[str, Any]  #: ... and its fsspec options
    project_root: str  #: imported first, so the stage's modules resolve ("" in shipped jobs)
    key: str  #: the artifact's cache key
    stage: str  #: stage name (messages, records)
    uses: str  #: ``package.module:Class``
    params: dict[str, Any]  #: canonical (validated) params
    inputs: dict[str, JobInput | None]
    force: bool = False  #: replace an existing artifact of the key
    #: the runner found no artifact of the key before submitting; False when it left that check to the worker
    #: (a remote store, and an input just computed: ``Runner.needs_check``), so the artifact found is no
    #: concurrent run's
    checked: bool = True
    jobs: int = 1  #: the run's worker count, given to the stage as ``Stage.jobs`` (not part of the key)
    key_parts: dict[str, Any] | None = None  #: what the key hashes, kept in the manifest
    #: shipped jobs (msflow.shipping): the content hash of the project code (stage modules and resources) among
    #: the store's blobs; the worker imports it from its own cache instead of ``project_root``
    code: str | None = None
    #: the stage may run in the run's own process (``Stage.in_process``): ``-j N`` runs it there when that is free
    in_process: bool = False
    #: the stage is quick (``Stage.cheap``): ``-j N`` starts no worker process for it
    cheap: bool = False

    def to_json(self) -> str:
        value = shallow_dict(self)
        value["inputs"] = {k: None if v is None else shallow_dict(v) for k, v in self.inputs.items()}
        return json.dumps(value, allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> Job:
        value = json.loads(text)
        inputs = {k: None if v is None else JobInput.from_json(v) for k, v in value.pop("inputs").items()}
        return cls(**value, inputs=inputs)


@dataclass
class Outcome:
    """What became of a job: its status and manifest, or the error (a user error is a dict from
    ``UserError.to_json``; a crash has a message and a traceback)."""

    status: StageStatus
    manifest: dict[str, Any] | None = None
    concurrent: bool = False  #: cached because another run computed the key while this one waited
    compute_seconds: float = 0.0  #: time in the stage's ``run``
    seconds: float = 0.0  #: time in the worker, store included
    pid: int | None = None  #: the worker process
    worker: str | None = None  #: where it ran: a Dask worker's address, or "<host> pid <pid>"
    attempts: int = 1  #: executions started (more than one when a worker died mid-stage and the task was retried)
    cpu_seconds: float = 0.0  #: CPU (user + system) of the worker and of processes it waited for, in ``run``
    error: str | None = None
    user_error: dict[str, Any] | None = field(default=None)
    traceback: str | None = None
    corrupt: dict[str, str] | None = None  #: an input artifact failed its integrity check: {"key", "problem"}

    def to_json(self) -> str:
        return json.dumps(shallow_dict(self), allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> Outcome:
        value = json.loads(text)
        return cls(**{**value, "status": StageStatus(value["status"])})

    @classmethod
    def crashed(cls, error: str, traceback: str | None = None) -> Outcome:
        return cls(StageStatus.FAILED, error=error, traceback=traceback)


def shallow_dict(obj: Any) -> dict[str, Any]:
    """A dataclass's fields as a dict, values as they are: ``dataclasses.asdict`` deep-copies every nested dict
    first (a manifest's meta, the key parts), 9-12x the cost of the JSON itself, on every job and outcome."""
    return {f.name: getattr(obj, f.name) for f in fields(obj)}
