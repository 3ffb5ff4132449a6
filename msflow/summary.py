"""A pipeline's ``summary:``, the stage metrics ``msflow run`` prints when it ends (the run's result, on stdout).

An entry is ``stage.metric``, the metric part a shell-style pattern (``capture_eval.mouth_*``). The spec checks the
stage names when the pipeline is loaded; the metric names are known only once the stage has run, so a name that is
none of them is a warning then, listing what there is (a pattern may match none: metrics that only some data
give). ``msflow sweep`` takes the same patterns as its default columns. Before the metrics come the lines naming
the files the run's ``publish:`` entries wrote and those already up to date (``published_lines``). Standard library
only: the no-op fast path prints lines saved by a full run.
"""

from __future__ import annotations

import fnmatch
import json
import math
from typing import Any

from msflow.errors import display_path

WILDCARDS = set("*?[")


def summary_entries(patterns: list[str], stages: dict[str, dict[str, Any]]) -> tuple[list[tuple[str, Any]], list[str]]:
    """([(``stage.metric``, value)], warnings) for the metrics of a run record's ``stages`` that ``patterns``
    match: in the patterns' order, each pattern's matches sorted, every metric once. Stages that did not finish
    (failed, skipped, not selected) are passed over: the run reports those itself."""
    found: dict[str, Any] = {}
    warnings = []
    for pattern in patterns:
        stage, _, metric_pattern = pattern.partition(".")
        record = stages.get(stage)
        if record is None or record.get("state") not in ("ran", "cached"):
            continue
        metrics = record.get("metrics") or {}
        names = sorted(n for n in metrics if fnmatch.fnmatchcase(n, metric_pattern))
        if not names and not WILDCARDS & set(metric_pattern):  # a pattern may match none (face.unseen_*: none unseen)
            known = ", ".join(sorted(metrics)[:12]) + (", ..." if len(metrics) > 12 else "")
            warnings.append(
                f"summary: '{pattern}' is no metric of stage '{stage}' ({f'its metrics: {known}' if metrics else 'it has none'})"
            )
        for name in names:
            found.setdefault(f"{stage}.{name}", metrics[name])
    return list(found.items()), warnings


def summary_lines(patterns: list[str], stages: dict[str, dict[str, Any]]) -> tuple[list[str], list[str]]:
    """``summary_entries`` as aligned lines ``stage.metric  value``, and the warnings."""
    entries, warnings = summary_entries(patterns, stages)
    width = max((len(n) for n, _ in entries), default=0)
    return [f"{name:<{width}}  {format_metric(value)}" for name, value in entries], warnings


def format_metric(value: Any) -> str:
    """A metric as a table cell: floats to 4 significant digits, others as JSON (long ones cut)."""
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    text = json.dumps(value, separators=(", ", ": "))
    return text if len(text) <= 80 else text[:77] + "..."


def published_lines(files: list[str], written: list[str]) -> list[str]:
    """Where the run's ``publish:`` entries put their ``files`` (relative to the working folder when inside it):
    ``published: out/a.glb`` for those the run ``written``, ``published files up to date: out/a.csv`` for those
    that held the same output already and were left alone (all of them after a run that changed nothing)."""
    fresh = [f for f in files if f in written]
    kept = [f for f in files if f not in written]
    lines = ["published: " + ", ".join(display_path(f) for f in fresh)] if fresh else []
    if kept:
        lines.append("published files up to date: " + ", ".join(display_path(f) for f in kept))
    return lines
