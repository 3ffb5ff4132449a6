"""Garbage collection: keep what the most recent runs reference, drop the rest, clear leftovers of killed runs."""
from __future__ import annotations

import os


def referenced_keys(store, keep_runs: int) -> set[str]:
    keys: set[str] = set()
    for run_id in store.run_ids()[-keep_runs:] if keep_runs > 0 else []:
        try:
            record = store.read_run(run_id)
        except Exception:  # noqa: BLE001 - an unreadable record references nothing
            continue
        keys.update(s["key"] for s in record.get("stages", {}).values() if s.get("key"))
    return keys


def _size(path) -> int:
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(dirpath, f))
            except OSError:
                pass
    return total


def collect_garbage(store, *, keep_runs: int = 10, dry_run: bool = False) -> dict:
    keep = referenced_keys(store, keep_runs)
    doomed = [k for k in store.keys() if k not in keep]
    freed = sum(_size(store.artifact_path(k)) for k in doomed) if hasattr(store, "artifact_path") else 0
    tmp: list[str] = []
    if not dry_run:
        for key in doomed:
            with store.lock(key):
                store.remove(key)
        tmp = store.clean_tmp()
    return {"artifacts": doomed, "bytes": freed, "kept": len(keep), "tmp": tmp}
