"""Who last published each file: the pipeline file and ``publish:`` entry behind every file a run published.

Two pipelines of a project may publish to the same file (``pipelines/capture.yaml -S vars.take=../../sad.mp4``
writes out/sad_head_motion.bvh, which pipeline.yaml publishes too); each run would silently replace the other's
result. The ledger lets a run say so: replacing a file last published by another pipeline file, or by another
entry (another stage output), is a warning; a new result of the same pipeline and entry (a parameter changed) is
the normal case and stays silent.

The ledger is ``published.json`` in the store's local cache (beside the memo): strict JSON, published path
(relative to the project) -> ``{"pipeline": path relative to the project, "entry": "stage.output"}``, written
atomically. Losing it (or a damaged one, read as empty) only costs the warnings until files are published again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from pathlib import Path
from typing import TYPE_CHECKING

from msflow.atomic import write_json_atomic
from msflow.spec import rel_to
from msflow.stores.base import json_object

if TYPE_CHECKING:
    from msflow.session import Session

LEDGER_NAME = "published.json"

Publisher = dict[str, str]  #: {"pipeline": "pipelines/capture.yaml", "entry": "export.head_bvh"}


@dataclasses.dataclass
class Publication:
    """What a run's ``publish:`` entries did."""

    #: the files they hold now: written by this run or already holding its output
    files: list[str] = dataclasses.field(default_factory=list)
    #: those of ``files`` this run wrote (the others held the same output already and were left alone)
    written: list[str] = dataclasses.field(default_factory=list)
    #: a file that another pipeline file or entry had published, replaced (``PublisherLedger.claim``)
    warnings: list[str] = dataclasses.field(default_factory=list)


def read_ledger(path: Path) -> dict[str, Publisher]:
    """The ledger's entries; {} when it is missing or unreadable (it only feeds warnings)."""
    try:
        data = json_object(path.read_bytes())
    except (OSError, ValueError):
        return {}
    return {k: v for k, v in data.items() if isinstance(v, dict) and {"pipeline", "entry"} <= set(v)}


class PublisherLedger:
    """The ledger as one run sees it: ``claim`` each file the run publishes, then ``save``."""

    def __init__(self, session: Session):
        cache = session.store.local_cache
        self.path = cache / LEDGER_NAME if cache is not None else None
        self.root = session.pipeline.root
        self.pipeline = session.pipeline.rel_path
        self.known = read_ledger(self.path) if self.path is not None else {}
        self.claimed: dict[str, Publisher] = {}

    def claim(self, dest: str, entry: str, replaced: bool) -> str | None:
        """Record this run's pipeline and ``entry`` as the publisher of ``dest``; the warning to give when the run
        ``replaced`` a file that another pipeline file or entry published, else None."""
        rel = rel_to(Path(dest), self.root)
        mine = {"pipeline": self.pipeline, "entry": entry}
        before = self.known.get(rel)
        self.claimed[rel] = self.known[rel] = mine
        if not replaced or before is None or before == mine:
            return None
        return f"{rel} was published by {before['pipeline']} ({before['entry']}); replaced by {self.pipeline} ({entry})"

    def save(self) -> None:
        """Merge this run's claims into the ledger as it is now on disk (another run may have written it since
        this one read it) and write it atomically. A read-only store still runs; it only loses the warnings."""
        if self.path is None or not self.claimed:
            return
        current = read_ledger(self.path)
        if all(current.get(rel) == mine for rel, mine in self.claimed.items()):
            return  # nothing new: a no-op run writes nothing
        current.update(self.claimed)
        with contextlib.suppress(OSError):
            os.makedirs(self.path.parent, exist_ok=True)
            write_json_atomic(self.path, current, indent=1)
