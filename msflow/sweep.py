"""Parameter sweeps: grids, zipped and explicit variants, run together with shared work, and results tables.

    msflow sweep pipeline.yaml -S keyshapes.k=10,20,30 -S bilinear.content_dim=4,8
    msflow sweep pipeline.yaml --grid sweep.yaml

A grid file::

    grid:                 # cartesian product (a list of such mappings: the union of their products)
      keyshapes.k: [10, 20, 30]
    zip:                  # varied together, row by row (all lists of one length), crossed with the grid
      trellis.b: [0.05, 0.1]
      trellis.c: [0.3, 0.2]
    variants:             # explicit extra variants
      - {keyshapes.k: 5, edit.smooth: 1.0}

Every variant is a normal run with its own record (``variant`` holds its parameters, ``sweep`` the sweep id). All
variants are scheduled together on one executor: a stage with the same cache key in several variants runs once.
"""

from __future__ import annotations

import fnmatch
import itertools
import json
import time
import uuid
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msflow.errors import UserError
from msflow.jobs import StageStatus
from msflow.runner import StopRun

if TYPE_CHECKING:
    from msflow.api import Execution
    from msflow.progress import SweepReporter
    from msflow.runner import Reporter, StageState
    from msflow.session import Session
    from msflow.stores.base import Store

GRID_KEYS = {"grid", "zip", "variants"}


def parse_values(text: str) -> tuple[str, list[Any]]:
    """``stage.param=v1,v2`` -> ("stage.param", [v1, v2]); values are YAML (``[1,2],[3,4]`` is two lists)."""
    import yaml

    from msflow.spec import UniqueKeyLoader

    if "=" not in text:
        raise UserError(f"bad sweep parameter '{text}': expected stage.param=value1,value2,...", field="-S")
    target, _, raw = text.partition("=")
    target = target.strip()
    if target.count(".") < 1 or not all(target.split(".")):
        raise UserError(f"bad sweep parameter '{text}': the target must be stage.param", field="-S")
    try:
        values = yaml.load(f"[{raw}]", Loader=UniqueKeyLoader)
    except yaml.YAMLError:
        values = [v.strip() for v in raw.split(",")]
    if not values:
        raise UserError(f"sweep parameter '{target}' has no values: the grid is empty", field="-S")
    return target, values


def grid_product(axes: dict[str, list[Any]]) -> list[dict[str, Any]]:
    if not axes:
        return [{}]
    names = list(axes)
    return [dict(zip(names, combo)) for combo in itertools.product(*(axes[n] for n in names))]


def load_grid_file(path: Path) -> list[dict[str, Any]]:
    from msflow.spec import parse_yaml

    file = str(path)
    if not path.is_file():
        raise UserError("grid file not found", file=file)
    doc = parse_yaml(path.read_text(encoding="utf-8"), file)
    if not isinstance(doc, dict) or not doc:
        raise UserError("a grid file is a mapping with 'grid', 'zip' and/or 'variants'", file=file)
    unknown = set(doc) - GRID_KEYS
    if unknown:
        raise UserError(
            f"unknown key(s) {sorted(unknown)}; allowed: grid, zip, variants", file=file, field=sorted(unknown)[0]
        )
    grids = doc.get("grid") or {}
    grids = grids if isinstance(grids, list) else [grids]
    base: list[dict[str, Any]] = []
    for i, grid in enumerate(grids):
        if not isinstance(grid, dict):
            raise UserError("each grid is a mapping stage.param: [values]", file=file, field=f"grid[{i}]")
        for name, values in grid.items():
            if not isinstance(values, list) or not values:
                raise UserError("needs a non-empty list of values", file=file, field=f"grid.{name}")
        base.extend(grid_product(grid))
    if not grids:
        base = [{}]
    zipped = doc.get("zip") or {}
    if zipped:
        if not isinstance(zipped, dict):
            raise UserError("zip is a mapping stage.param: [values]", file=file, field="zip")
        lengths = {n: len(v) if isinstance(v, list) else -1 for n, v in zipped.items()}
        if len(set(lengths.values())) != 1 or -1 in lengths.values() or 0 in lengths.values():
            raise UserError(f"zipped lists must be non-empty and of one length, got {lengths}", file=file, field="zip")
        rows = [dict(zip(zipped, row)) for row in zip(*zipped.values())]
        base = [{**b, **r} for b in base for r in rows]
    explicit = doc.get("variants") or []
    if not isinstance(explicit, list) or not all(isinstance(v, dict) for v in explicit):
        raise UserError("variants is a list of mappings stage.param: value", file=file, field="variants")
    if not doc.get("grid") and not zipped:
        base = []
    variants = base + [dict(v) for v in explicit]
    if not variants:
        raise UserError("the grid is empty: no variant to run", file=file)
    return variants


def expand_variants(cli: list[str], grid_file: Path | None) -> list[dict[str, Any]]:
    """Variants from ``-S`` (comma lists form a grid) crossed with the grid file's variants."""
    axes: dict[str, list[Any]] = {}
    for text in cli:
        target, values = parse_values(text)
        axes[target] = values
    variants = grid_product(axes)
    if grid_file is not None:
        from_file = load_grid_file(grid_file)
        variants = [{**v, **f} for v in variants for f in from_file]
    if not variants or (not cli and grid_file is None):
        raise UserError("the grid is empty: give -S stage.param=v1,v2 or --grid FILE", field="-S")
    return variants


def variant_overrides(variant: dict[str, Any]) -> list[str]:
    return [f"{target}={json.dumps(value)}" for target, value in variant.items()]


@dataclass
class VariantOutcome:
    index: int
    params: dict[str, Any]
    run_id: str | None = None
    ok: bool = False
    error: str | None = None
    metrics: dict[str, dict[str, Any]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)


@dataclass
class SweepResult:
    sweep_id: str
    pipeline: str
    variants: list[VariantOutcome]
    seconds: float
    executed: int  # stage executions across all variants
    unique_keys: int  # distinct cache keys across all variants
    summary: list[str] = field(default_factory=list)  # the pipeline's summary: patterns, the default columns

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.sweep_id,
            "pipeline": self.pipeline,
            "seconds": self.seconds,
            "executed": self.executed,
            "unique_keys": self.unique_keys,
            "summary": self.summary,
            "variants": [vars(v) for v in self.variants],
        }


def run_sweep(
    path: str | Path,
    variants: list[dict[str, Any]],
    *,
    base_overrides: Sequence[str] = (),
    jobs: int = 1,
    executor: str = "local",
    scheduler: str | None = None,
    connect_timeout: float = 10.0,
    reporter: SweepReporter | None = None,
    sort: str | None = None,
) -> SweepResult:
    """Validate every variant and ``sort`` (the column of ``results_rows``; nothing runs if one is invalid), then
    run them together on one executor (``msflow.api.run_sessions``, the path of ``msflow run`` too). A ``sort``
    metric the stage does not give stops the sweep the first time that stage finishes (``SortMetricCheck``)."""
    from msflow.api import run_sessions
    from msflow.stores.base import new_run_id

    started = time.time()
    sessions = open_variant_sessions(path, variants, base_overrides)
    sort_check = check_sort(sort, variants, sessions[0].pipeline.stages)
    reporters = [
        reporter.for_variant(i, v, len(s.pipeline.stages)) if reporter is not None else None
        for i, (v, s) in enumerate(zip(variants, sessions))
    ]
    if sort_check is not None:
        reporters = [sort_check.watching(r) for r in reporters]
    sweep_id = new_run_id()
    executions = run_sessions(
        sessions,
        jobs=jobs,
        executor=executor,
        scheduler=scheduler,
        connect_timeout=connect_timeout,
        reporters=list(reporters),
        labels=variants,
        extra={"sweep": sweep_id},
    )
    outcomes = [variant_outcome(index, variants[index], e) for index, e in enumerate(executions)]
    keys = {s.key for e in executions for s in e.states.values() if s.key}
    executed = sum(1 for e in executions for s in e.states.values() if s.state is StageStatus.RAN)
    result = SweepResult(
        sweep_id,
        sessions[0].pipeline.rel_path,
        outcomes,
        time.time() - started,
        executed,
        len(keys),
        list(sessions[0].pipeline.summary),
    )
    _write_sweep_record(sessions[0].store, result)
    return result


# ---------------------------------------------------------------------------------------------------------- sorting
def sort_column(sort: str) -> tuple[str, bool]:
    """``--sort`` -> (column, descending): ``-column`` sorts descending.

    >>> sort_column("-total.total"), sort_column("src.n")
    (('total.total', True), ('src.n', False))
    """
    descending = sort.startswith("-")
    return sort.lstrip("-"), descending


def swept_params(variants: Sequence[dict[str, Any]]) -> list[str]:
    """The parameters the variants set, in first-seen order: the table's parameter columns."""
    return list(dict.fromkeys(t for v in variants for t in v))


@dataclass
class SortMetricCheck:
    """``--sort stage.metric``, checked the first time the stage finishes in any variant. Stages do not declare
    their metrics, so that is the earliest the name can be checked; a misspelt one then stops the sweep (msflow
    sweep: exit 2) instead of being found after every variant ran."""

    column: str
    stage: str
    metric: str
    checked: bool = False

    def see(self, state: StageState) -> None:
        """Check the metric on the stage's first finished result; raises ``StopRun`` when it is not there."""
        if self.checked or state.name != self.stage or not state.state.done:
            return
        self.checked = True
        from msflow.spec import suggest

        metrics = sorted((state.manifest or {}).get("metrics", {}))
        if self.metric not in metrics:
            given = f"its metrics: {', '.join(metrics)}" if metrics else "it gives none"
            message = f"stage '{self.stage}' gives no metric '{self.metric}'{suggest(self.metric, metrics)}; {given}"
            raise StopRun(UserError(f"cannot sort by '{self.column}': {message}", field="--sort"))

    def watching(self, reporter: Reporter | None) -> Reporter:
        """``reporter`` (or none), with this check looking at every state change it is given."""
        check = self

        class Watching:
            def update(self, state: StageState) -> None:
                if reporter is not None:
                    reporter.update(state)
                check.see(state)

        return Watching()


def check_sort(sort: str | None, variants: Sequence[dict[str, Any]], stages: Collection[str]) -> SortMetricCheck | None:
    """Check ``--sort`` before any variant runs, as far as it can be: a swept parameter, or ``stage.metric`` of a
    stage of the pipeline. Returns the check of the metric's name that has to wait for the stage's result (None
    when there is nothing left to check)."""
    if not sort:
        return None
    column, _ = sort_column(sort)
    params = swept_params(variants)
    if column in params:
        return None
    stage, dot, metric = column.partition(".")
    swept = f"a swept parameter ({', '.join(params)})"
    if not (stage and dot and metric):
        raise UserError(f"cannot sort by '{column}': give {swept} or stage.metric", field="--sort")
    if stage not in stages:
        from msflow.spec import unknown_stage

        problem = f"not {swept}, and {unknown_stage(stage, stages)}"
        raise UserError(f"cannot sort by '{column}': {problem}", field="--sort")
    return SortMetricCheck(column, stage, metric)


def open_variant_sessions(
    path: str | Path, variants: list[dict[str, Any]], base_overrides: Sequence[str]
) -> list[Session]:
    """One session per variant (its overrides after ``base_overrides``), sharing one memo; an invalid variant is a
    user error naming it, before anything runs."""
    from msflow.session import open_session

    sessions: list[Session] = []
    memo = None
    for index, variant in enumerate(variants):
        try:
            session = open_session(path, [*base_overrides, *variant_overrides(variant)], memo=memo)
        except UserError as exc:
            raise UserError(
                f"variant {index + 1} {variant}: {exc.message}", file=exc.file, stage=exc.stage, field=exc.field
            ) from None
        memo = session.memo
        sessions.append(session)
    return sessions


def variant_outcome(index: int, params: dict[str, Any], execution: Execution) -> VariantOutcome:
    """What became of one variant: its run, whether it failed (and the first failed stage's error), its metrics."""
    record = execution.record
    failed = [s for s in execution.states.values() if s.state is StageStatus.FAILED]
    return VariantOutcome(
        index,
        params,
        record["id"],
        not failed,
        failed[0].error if failed else None,
        {n: s["metrics"] for n, s in record["stages"].items() if s["metrics"]},
        record["counts"],
    )


def _write_sweep_record(store: Store, result: SweepResult) -> None:
    record = {"id": result.sweep_id, "kind": "sweep", **result.to_json()}
    store.write_sweep(record)


# ---------------------------------------------------------------------------------------------------------- tables
def metric_columns(result: SweepResult, patterns: list[str] | None) -> list[str]:
    names = sorted({f"{stage}.{m}" for v in result.variants for stage, ms in v.metrics.items() for m in ms})
    if patterns:
        return [n for n in names if any(fnmatch.fnmatch(n, p) for p in patterns)]
    swept_stages = {t.split(".")[0] for v in result.variants for t in v.params}
    # a metric that only echoes a swept parameter of the same name adds nothing to the table
    echoes = {n for n in names if all(v.params.get(n, object()) == variant_metric(v, n) for v in result.variants)}
    varying = [
        n for n in names if n not in echoes and len({json.dumps(variant_metric(v, n)) for v in result.variants}) > 1
    ]
    return varying or [n for n in names if n.split(".")[0] in swept_stages and n not in echoes]


def variant_metric(variant: VariantOutcome, column: str) -> Any:
    stage, _, name = column.partition(".")
    return variant.metrics.get(stage, {}).get(name)


def results_rows(result: SweepResult, metrics: list[str], sort: str | None = None) -> tuple[list[str], list[list[Any]]]:
    """(header, rows) of the results table: variant number, parameters, status and the ``metrics`` columns, in
    the order of ``sort`` (``sort_column``); a metric sorted by is shown even when ``metrics`` leaves it out."""
    params = swept_params([v.params for v in result.variants])
    columns = list(metrics)
    variants = list(result.variants)
    if sort:
        column, descending = sort_column(sort)
        if (
            column not in params
            and column not in columns
            and any(variant_metric(v, column) is not None for v in variants)
        ):
            columns.append(column)
        if column in params or column in columns:
            variants.sort(key=lambda v: _sort_key(v, column, column in params, descending))
        elif any(v.ok for v in variants):  # when none is, the stage never finished: nothing to sort by
            raise UserError(
                f"cannot sort by '{column}': not a column; columns: {', '.join(params + columns)}", field="--sort"
            )
    rows = [
        [
            v.index + 1,
            *[v.params.get(p) for p in params],
            "ok" if v.ok else f"failed: {v.error}",
            *[variant_metric(v, m) for m in columns],
        ]
        for v in variants
    ]
    return ["#", *params, "status", *columns], rows


def _sort_key(variant: VariantOutcome, column: str, is_param: bool, descending: bool) -> tuple[bool, Any]:
    """Missing values last, whichever the direction."""
    value = variant.params.get(column) if is_param else variant_metric(variant, column)
    return (value is None, -value if descending and isinstance(value, (int, float)) else value)


FORMATS = ("table", "md", "csv", "json")


def check_format(fmt: str) -> None:
    """A results table format ``format_table`` writes, or a user error (``msflow sweep`` checks it first)."""
    if fmt not in FORMATS:
        raise UserError(f"unknown format '{fmt}'; choose {', '.join(FORMATS[:-1])} or {FORMATS[-1]}", field="--format")


def format_table(header: list[str], rows: list[list[Any]], fmt: str) -> str:
    check_format(fmt)
    if fmt == "json":
        return json.dumps([dict(zip(header, r)) for r in rows], indent=1)
    if fmt == "csv":
        import csv
        import io

        buf = io.StringIO()
        writer = csv.writer(buf)
        writer.writerow(header)
        writer.writerows(rows)
        return buf.getvalue()
    cells = [[format_value(c) for c in r] for r in rows]
    if fmt == "md":
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in cells]
        return "\n".join(lines)
    if "status" in header:  # a failed variant's error would stretch its column: failure_lines has it whole
        at = header.index("status")
        for row in cells:
            row[at] = shorten(row[at], STATUS_WIDTH)
    widths = [max(len(str(h)), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    lines = ["  ".join(str(h).ljust(w) for h, w in zip(header, widths))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


#: the widest status cell of a ``table``: "failed: " and the start of the error (failure_lines prints it whole)
STATUS_WIDTH = 48


def shorten(text: str, width: int) -> str:
    """``text`` on one line, cut to ``width`` characters with an ellipsis when longer.

    >>> shorten("failed: RuntimeError: boom", 40), shorten("failed: a long\nerror", 12)
    ('failed: RuntimeError: boom', 'failed: a l…')
    """
    line = " ".join(text.split())
    return line if len(line) <= width else line[: width - 1] + "…"


def failure_lines(result: SweepResult) -> list[str]:
    """One line per failed variant, ``variant N (stage.param=value, ...): error``: the errors the ``table``
    format cuts short, printed below it."""
    lines = []
    for variant in result.variants:
        if not variant.ok:
            described = ", ".join(f"{k}={v}" for k, v in variant.params.items())
            lines.append(f"variant {variant.index + 1} ({described}): {' '.join(str(variant.error).split())}")
    return lines


def format_value(value: object, digits: int = 4) -> str:
    """A table cell: floats to ``digits`` significant digits, None as "-", anything else as str.

    >>> format_value(3.14159), format_value(None), format_value(12)
    ('3.142', '-', '12')
    """
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def new_sweep_id() -> str:
    return uuid.uuid4().hex[:8]
