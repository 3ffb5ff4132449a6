"""Garbage collection: keep what the most recent runs reference, drop the rest, clear leftovers of killed runs
and the damaged artifacts runs set aside."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from msflow.stores.base import Store


def referenced_keys(store: Store, keep_runs: int) -> set[str]:
    """Stage keys the newest ``keep_runs`` run records reference."""
    keys: set[str] = set()
    for run_id in store.run_ids()[-keep_runs:] if keep_runs > 0 else []:
        try:
            record = store.read_run(run_id)
        except Exception:
            continue
        keys.update(s["key"] for s in record.get("stages", {}).values() if s.get("key"))
    return keys


def parts_of(store: Store, keys: set[str]) -> set[str]:
    """The parts (msflow.parts) the artifacts of ``keys`` were built from: kept as long as those are."""
    from msflow.parts import parts_named

    found: set[str] = set()
    for key in keys:
        try:
            found.update(parts_named(store.manifest(key)))
        except Exception:  # missing or corrupt: it names nothing to keep
            continue
    return found


def figure_of(store: Store, key: str, keep: set[str]) -> bool:
    """Whether ``key`` is a cached report figure of a kept stage artifact (figures name their stage's key)."""
    try:
        meta = store.manifest(key).get("meta")
    except Exception:  # a corrupt artifact is no figure to keep
        return False
    return isinstance(meta, dict) and meta.get("stage_key") in keep


def collect_garbage(store: Store, *, keep_runs: int = 10, dry_run: bool = False) -> dict[str, Any]:
    """Remove artifacts that none of the newest ``keep_runs`` runs references (report figures of the artifacts
    they reference stay too), leftovers of killed writers, and the damaged artifacts set aside
    (``Store.quarantine``), whose reasons the runs that found them reported."""
    with store.in_use(alone=True):  # a run in progress has made artifacts no record names yet
        return _collect(store, keep_runs=keep_runs, dry_run=dry_run)


def _collect(store: Store, *, keep_runs: int, dry_run: bool) -> dict[str, Any]:
    """What gc did (or, with ``dry_run``, would do): ``artifacts`` the keys removed and ``bytes`` their size,
    ``kept`` how many artifacts stay in the store (counted there: a key a record names may be gone already, and
    the figures and parts of kept artifacts stay too), ``tmp`` the leftovers of killed writers cleared (none in a
    dry run, which clears nothing), ``damaged`` and ``damaged_bytes`` the artifacts set aside that were deleted."""
    keep = referenced_keys(store, keep_runs)
    keep |= parts_of(store, keep)
    stored = list(store.keys())
    doomed = [k for k in stored if k not in keep and not figure_of(store, k, keep)]
    freed = sum(store.size(k) for k in doomed)
    tmp: list[str] = []
    if not dry_run:
        for key in doomed:
            with store.lock(key):
                store.remove(key)
        tmp = store.clean_tmp()
    damaged, damaged_bytes = store.drop_quarantined(dry_run=dry_run)
    return {
        "artifacts": doomed,
        "bytes": freed,
        "kept": len(stored) - len(doomed),
        "tmp": tmp,
        "damaged": damaged,
        "damaged_bytes": damaged_bytes,
    }
