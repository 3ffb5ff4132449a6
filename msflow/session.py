"""A session: a loaded, resolved pipeline with its store and memo, what every command starts from."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msflow.hashing import json_hash
from msflow.plan import StagePlan, resolve
from msflow.spec import Pipeline, load_pipeline
from msflow.stores.base import Store

MEMO_ENTRIES = 2000  # per memo section; an evicted entry is only recomputed (one parse, import or file hash)


def trim_memo(memo: dict[str, Any]) -> None:
    """Keep each growing memo section to its newest entries: every code edit adds fingerprints, interfaces and
    params that later runs never ask for again, and the memo is read by every no-op run."""
    sections = [memo.get(k) for k in ("interfaces", "params", "data", "published", "records")]
    code = memo.get("code") or {}
    sections += [code.get("files"), code.get("closures")]
    for section in sections:
        if isinstance(section, dict) and len(section) > MEMO_ENTRIES:
            for key in list(section)[: len(section) - MEMO_ENTRIES]:
                del section[key]


@dataclass
class Session:
    """A loaded, resolved pipeline with its store and memo: what every command starts from."""

    def __repr__(self) -> str:
        return f"Session({self.pipeline.rel_path}, {len(self.plans)} stages, store {self.store.url})"

    pipeline: Pipeline
    store: Store
    memo: dict[str, Any]
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


def open_session(
    path: str | Path,
    overrides: Sequence[str] = (),
    memo: dict[str, Any] | None = None,
    publish_dir: str | Path | None = None,
) -> Session:
    """Load and resolve a pipeline; ``memo`` shares one memo between sessions (sweep variants); ``publish_dir``
    is where ``publish:`` entries go instead of the pipeline's folder."""
    pipeline = load_pipeline(path, tuple(overrides), publish_dir)
    store = pipeline.open_store()
    memo = store.load_memo() if memo is None else memo
    digest = json_hash(memo)
    plans = resolve(pipeline, memo)
    return Session(pipeline, store, memo, plans, digest)
