"""Parts: pieces of a stage's result that depend on one label of its inputs, stored and reused on their own.

A stage over a folder of takes is keyed by all of them, so adding one clip changes its key and the whole stage
runs again. A stage whose takes are independent asks for each take as a part (``Stage.part``): the part's key
hashes only what the part may read (the stage's class, code, params and resources, the entry of each
``labelled`` input under the part's label, and each ``whole`` input), and the part is an artifact of its own in
the store under that key. The next run with one more clip finds the other takes' parts and copies them instead
of computing them again.

The label's name itself is not in the key (what a part holds must not depend on it), so renaming a label or
listing the same video under two labels reuses its part. The stage artifact names the parts it was built from
(manifest ``parts``), which keeps them through ``msflow gc`` as long as the artifact is kept. A part found
damaged is set aside and computed again, with a warning. The ``UserWarning``s a part's computation raised are kept
with it and said again whenever it is used, so the stage's warnings (and content hash) do not depend on which parts
an earlier run computed.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any, Protocol

from msflow.hashing import json_hash

if TYPE_CHECKING:
    from msflow.sinks import OutputSink
    from msflow.stores.base import Store

PART_SCHEME = 1  #: bump when what a part key hashes changes meaning

#: What a part's computation receives: opens a sink like ``Stage.sink`` (name, dtype, row_shape), writing into
#: the part's own artifact.
SinkFactory = Callable[..., "OutputSink"]
#: A part's computation as a source runs it: given a sink factory, the part's arrays and strict-JSON meta
#: (``Stage.part`` checks the stage's ``Result`` into this form).
MakePart = Callable[[SinkFactory], tuple[Mapping[str, Any], dict[str, Any]]]


@dataclass
class Part:
    """A part as the stage gets it back: arrays by name (lazy stored arrays when it is in a store, numpy
    otherwise), its JSON metadata, its key (None outside a store), whether it was found already computed, and the
    warnings its computation raised (kept with a stored part: said again when it is reused)."""

    arrays: Mapping[str, Any]
    meta: dict[str, Any]
    key: str | None = None
    reused: bool = False
    warnings: list[str] = field(default_factory=list)


class PartSource(Protocol):
    """Where a stage's parts are found and kept (``StoreParts`` in a store run; ``InMemoryParts`` otherwise)."""

    def get(self, label: str, make: MakePart, reads: PartReads) -> Part: ...


@dataclass(frozen=True)
class PartReads:
    """What a part's computation reads besides the stage's class, code and resources: the entry under its label of
    each ``labelled`` files input, each ``whole`` input, and every param but the ``unread_params``."""

    labelled: tuple[str, ...]
    whole: tuple[str, ...] = ()
    unread_params: tuple[str, ...] = ()


def part_key_parts(key_parts: Mapping[str, Any], label: str, reads: PartReads) -> dict[str, Any]:
    """What a part's key hashes: the stage key's scheme, class, code and resources, its params but those the part
    does not read; of each labelled files input only the entry under ``label`` (its content hash and fields, or
    None when it has none); each whole input as the stage key has it. Inputs named in neither are not in the key:
    the part must not read them."""
    inputs = key_parts.get("inputs") or {}
    chosen: dict[str, Any] = {}
    for name in reads.labelled:
        entry = inputs.get(name)
        files = entry.get("files", {}) if isinstance(entry, Mapping) else {}
        if label not in files:
            chosen[name] = None
            continue
        fields = (entry.get("fields") or {}).get(label) if isinstance(entry, Mapping) else None
        chosen[name] = {"file": files[label], "fields": fields or {}}
    for name in reads.whole:
        chosen[name] = inputs.get(name)
    same = {k: v for k, v in key_parts.items() if k in ("scheme", "class", "code", "resources")}
    params = {k: v for k, v in (key_parts.get("params") or {}).items() if k not in reads.unread_params}
    return {"part_scheme": PART_SCHEME, **same, "params": params, "inputs": chosen}


def check_part_reads(declared: Mapping[str, Any], params: Any, reads: PartReads) -> None:
    """A part names only declared inputs, each once, its labelled inputs are files (they have labels), and the
    params it does not read are params of the stage."""
    unknown = [n for n in (*reads.labelled, *reads.whole) if n not in declared]
    if unknown:
        raise ValueError(f"Stage.part: unknown inputs {unknown}; declared: {sorted(declared)}")
    twice = sorted(set(reads.labelled) & set(reads.whole))
    if twice:
        raise ValueError(f"Stage.part: inputs {twice} are both labelled and whole")
    not_files = [n for n in reads.labelled if getattr(declared[n], "kind", None) != "files"]
    if not_files:
        raise ValueError(f"Stage.part: labelled inputs must be files inputs, not {not_files}")
    fields = getattr(params, "model_fields", {})
    not_params = [n for n in reads.unread_params if n not in fields]
    if not_params:
        raise ValueError(f"Stage.part: unread_params {not_params} are no params of the stage; params: {sorted(fields)}")


class InMemoryParts:
    """Outside a store (``msflow.testing.run_stage``, a stage called directly): parts are computed, never kept."""

    def get(self, label: str, make: MakePart, reads: PartReads) -> Part:
        from msflow.artifact import settle_output
        from msflow.sinks import OutputSink

        def sink(name: str, *, dtype: Any, row_shape: tuple[int, ...] = ()) -> OutputSink:
            return OutputSink(name, dtype, tuple(row_shape))

        arrays, meta = make(sink)
        return Part({name: settle_output(value) for name, value in arrays.items()}, meta)


@dataclass
class StoreParts:
    """A store run's parts: looked up under their key's lock, computed and committed when missing or damaged."""

    store: Store
    key_parts: Mapping[str, Any]
    stage: str
    force: bool = False  #: ``msflow run --force STAGE``: compute every part again and replace the stored one
    #: called with the part's label and the lock's holder when another run is computing the part
    on_wait: Callable[[str, dict[str, Any]], None] | None = None
    used: dict[str, str] = field(default_factory=dict)  #: label -> part key, for the stage artifact's manifest
    reused: list[str] = field(default_factory=list)  #: labels whose part was found

    def get(self, label: str, make: MakePart, reads: PartReads) -> Part:
        parts = part_key_parts(self.key_parts, label, reads)
        key = json_hash(parts)
        waiting = None if self.on_wait is None else partial(self.on_wait, label)
        with self.store.lock(key, on_wait=waiting):
            found = None if self.force else self._found(key, label)
            part = found or self._compute(key, parts, label, make)
        self.used[label] = key
        if part.reused:
            self.reused.append(label)
        for message in part.warnings:  # into the stage's warnings, found or computed alike
            warnings.warn(message, UserWarning, stacklevel=3)
        return part

    def _found(self, key: str, label: str) -> Part | None:
        """The stored part, after checking its content; a damaged one is set aside (then None: compute it)."""
        from msflow.errors import CorruptArtifact

        if not self.store.has(key):
            return None
        try:
            problems = self.store.verify(key)
        except CorruptArtifact as exc:
            problems = [exc.problem]
        if problems:
            self.store.quarantine(key, f"stage '{self.stage}', part '{label}': {'; '.join(problems)}")
            warnings.warn(
                f"the stored part of '{label}' was damaged ({problems[0]}): set aside and computed again",
                UserWarning,
                stacklevel=4,
            )
            return None
        return self._open(key, reused=True)

    def _compute(self, key: str, parts: dict[str, Any], label: str, make: MakePart) -> Part:
        from msflow.sinks import OutputSink

        with self.store.writer(key) as writer:

            def sink(name: str, *, dtype: Any, row_shape: tuple[int, ...] = ()) -> OutputSink:
                return OutputSink(name, dtype, tuple(row_shape), writer)

            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                arrays, meta = make(sink)
            extra = {"meta": meta, "key": key, "stage": self.stage, "part": label, "key_parts": parts}
            said = part_warnings(caught)
            if said:  # kept with the part, said again by every stage that uses it (StoreParts.get)
                extra["warnings"] = said
            writer.commit(arrays, {**extra, "created": time.time()}, replace=self.force)
        return self._open(key, reused=False)

    def _open(self, key: str, *, reused: bool) -> Part:
        view = self.store.open(key)
        return Part({name: view.lazy(name) for name in view.names}, dict(view.meta), key, reused, view.warnings)


def part_warnings(caught: list[warnings.WarningMessage]) -> list[str]:
    """The ``UserWarning`` messages a part's computation raised, each once, to keep with it; other warnings go on
    to the stage's context now, as they would have without parts."""
    said = []
    for w in caught:
        if issubclass(w.category, UserWarning):
            said.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return list(dict.fromkeys(said))


def parts_named(manifest: Mapping[str, Any]) -> list[str]:
    """The part keys an artifact's manifest names (``msflow gc`` keeps them with it)."""
    parts = manifest.get("parts")
    keys = parts.get("keys") if isinstance(parts, Mapping) else None
    return [k for k in (keys or {}).values() if isinstance(k, str)]
