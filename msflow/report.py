"""The run report: one self-contained HTML page (images and video inline) of a run or a sweep.

Sections: the stage graph coloured by state with timings, resolved params and keys, metrics, then every stage's
figures. Figures are declared by stage classes (``Stage.figures``) and rendered from the run's artifacts with
matplotlib; each rendered figure is cached in the store under a key derived from its stage's cache key, so a second
report of the same run renders nothing.
"""

from __future__ import annotations

import base64
import html
import json
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msflow.atomic import write_atomic
from msflow.dag import STATE_COLOURS
from msflow.errors import CorruptArtifact, CorruptRecord, UserError
from msflow.hashing import json_hash
from msflow.jobs import StageStatus

if TYPE_CHECKING:
    from msflow.session import Session
    from msflow.spec import Pipeline
    from msflow.stores.base import Store
    from msflow.sweep import SweepResult

FIGURE_SCHEME = 1


@dataclass
class Figure:
    stage: str
    name: str
    media: str  # "image/png" | "video/mp4"
    data: bytes
    cached: bool
    seconds: float
    error: str | None = None


# ---------------------------------------------------------------------------------------------------------- figures
def figure_key(stage_key: str, uses: str, name: str) -> str:
    """A stage's key covers its code (figure functions included), params and input content."""
    return json_hash({"figure_scheme": FIGURE_SCHEME, "stage_key": stage_key, "uses": uses, "figure": name})


def to_media(result: Any) -> tuple[str, bytes]:
    """A figure function's return value as (media type, bytes)."""
    if isinstance(result, (bytes, bytearray, memoryview)):
        data = bytes(result)
        if data[:8] == b"\x89PNG\r\n\x1a\n":
            return "image/png", data
        if data[4:8] == b"ftyp":
            return "video/mp4", data
        if data[:4] == b"\x1aE\xdf\xa3":
            return "video/webm", data
        raise ValueError("figure returned bytes that are neither PNG, MP4 nor WebM")
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    result.savefig(buf, format="png", dpi=96, bbox_inches="tight")
    plt.close(result)
    return "image/png", buf.getvalue()


def stage_inputs(record: dict[str, Any], stage: str, store: Store, root: Path) -> dict[str, Any]:
    """The inputs a stage saw in a run, reopened from the store (artifacts) and the project (files)."""
    entry = record["stages"][stage]
    inputs: dict[str, Any] = {}
    for name, source in (entry.get("inputs") or {}).items():
        if "files" in source:
            inputs[name] = {label: root / rel for label, rel in source["files"].items()}
            continue
        upstream, _, output = source["from"].partition(".")
        upstream_entry = record["stages"].get(upstream)
        if not upstream_entry or not store.has(upstream_entry["key"]):
            continue
        view = store.open(upstream_entry["key"])
        inputs[name] = view[output] if output else view
    return inputs


def render_stage_figures(job: dict[str, Any]) -> list[dict[str, Any]]:
    """Render (or fetch from the cache) every figure of one stage. JSON in, JSON out: runs in a worker process."""
    import matplotlib

    matplotlib.use("Agg")
    from msflow.plan import ensure_importable, import_stage_class
    from msflow.stores import open_store

    ensure_importable(job["root"])
    store = open_store(job["store"], job.get("store_options"))
    record = job["record"]
    stage = job["stage"]
    entry = record["stages"][stage]
    cls = import_stage_class(entry["uses"], stage=stage, root=job["root"])
    out = []
    view = None
    inputs = None
    for name, func in cls.figures.items():
        key = figure_key(entry["key"], entry["uses"], name)
        started = time.perf_counter()
        if store.has(key):
            out.append(_cached_figure_item(store, key, name, started))
            continue
        try:
            if view is None:  # opened once, and only if some figure is not cached
                view = store.open(entry["key"])
                inputs = stage_inputs(record, stage, store, Path(job["root"]))
            media, data = to_media(func(view, inputs))
        except Exception as exc:
            out.append({"name": name, "error": f"{type(exc).__name__}: {exc}", "seconds": 0.0})
            continue
        meta = {"media": media, "stage": stage, "figure": name, "stage_key": entry["key"]}
        _store_figure(store, key, data, meta)
        out.append(
            {"name": name, "key": key, "media": media, "cached": False, "seconds": time.perf_counter() - started}
        )
    return out


def _cached_figure_item(store: Store, key: str, name: str, started: float) -> dict[str, Any]:
    """A worker's answer for a figure already in the store."""
    cached = store.open(key)
    return {
        "name": name,
        "key": key,
        "media": cached.meta["media"],
        "cached": True,
        "seconds": time.perf_counter() - started,
    }


def _store_figure(store: Store, key: str, data: bytes, meta: dict[str, Any]) -> None:
    """Write a rendered figure under its key, unless another worker wrote it meanwhile."""
    import numpy as np

    with store.lock(key):
        if not store.has(key):
            store.write(key, {"data": np.frombuffer(data, np.uint8)}, {"meta": meta})


def _render_job(job_json: str) -> str:
    from msflow.worker import single_threaded_blas

    with single_threaded_blas():
        return json.dumps(render_stage_figures(json.loads(job_json)))


def collect_figures(session: Session, record: dict[str, Any], jobs: int) -> list[Figure]:
    """Figures of every settled stage of a run, rendered in parallel worker processes when ``jobs`` > 1. A cached
    figure found damaged in the store is set aside (``Store.quarantine``) and drawn again, and counts as drawn."""
    stages = _settled_stages(session, record)
    payloads = {s: _render_payload(session, record, s) for s in stages}
    redrawn: set[str] = set()
    while True:
        results = _figure_items(session, record, stages, payloads, jobs)
        try:
            return _figures_from_items(session, stages, results, redrawn)
        except CorruptArtifact as exc:
            if not exc.key or exc.key in redrawn:
                raise
            session.store.quarantine(exc.key, f"report: {exc.problem}")
            redrawn.add(exc.key)


def _figure_items(
    session: Session, record: dict[str, Any], stages: list[str], payloads: dict[str, str], jobs: int
) -> dict[str, list[dict[str, Any]]]:
    """Each stage's figure items: from the store when all are cached, else from a worker that renders them."""
    results: dict[str, list[dict[str, Any]]] = {}
    pending = []
    for stage in stages:  # cheap pass: stages whose figures are all cached need no worker
        cached = _all_cached_items(session, stage, record["stages"][stage])
        if cached is None:
            pending.append(stage)
        else:
            results[stage] = cached
    results.update(_render_pending(payloads, pending, jobs))
    return results


def _settled_stages(session: Session, record: dict[str, Any]) -> list[str]:
    """The run's stages that ran or were cached and whose artifact is still in the store, in pipeline order."""
    return [
        s
        for s in session.pipeline.stages
        if record["stages"].get(s, {}).get("state") in (StageStatus.CACHED, StageStatus.RAN)
        and session.store.has(record["stages"][s]["key"])
    ]


def _render_payload(session: Session, record: dict[str, Any], stage: str) -> str:
    """The JSON job a figure worker gets for one stage (see ``render_stage_figures``)."""
    return json.dumps(
        {
            "root": str(session.pipeline.root),
            "store": session.store.url,
            "store_options": session.store.options,
            "record": _slim(record),
            "stage": stage,
        }
    )


def _all_cached_items(session: Session, stage: str, entry: dict[str, Any]) -> list[dict[str, Any]] | None:
    """The worker's answer for a stage whose declared figures are all in the store, or None if one is missing."""
    names = session.plans[stage].interface.get("figures") if stage in session.plans else None
    if names and all(session.store.has(figure_key(entry["key"], entry["uses"], n)) for n in names):
        return [
            {"name": n, "key": figure_key(entry["key"], entry["uses"], n), "cached": True, "seconds": 0.0}
            for n in names
        ]
    return None


def _render_pending(payloads: dict[str, str], pending: list[str], jobs: int) -> dict[str, list[dict[str, Any]]]:
    """Figure items of the ``pending`` stages: in a spawned process pool when ``jobs`` > 1 and it pays, else here."""
    results: dict[str, list[dict[str, Any]]] = {}
    if jobs > 1 and len(pending) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        from msflow.worker import pin_blas_threads

        pin_blas_threads()
        with ProcessPoolExecutor(
            max_workers=jobs, mp_context=multiprocessing.get_context("spawn"), initializer=pin_blas_threads
        ) as pool:
            futures = {s: pool.submit(_render_job, payloads[s]) for s in pending}
            for stage, future in futures.items():
                results[stage] = json.loads(future.result())
    else:
        for stage in pending:
            results[stage] = json.loads(_render_job(payloads[stage]))
    return results


def _figures_from_items(
    session: Session, stages: list[str], results: dict[str, list[dict[str, Any]]], redrawn: set[str]
) -> list[Figure]:
    """The workers' items as Figures, stage by stage in ``stages`` order, their bytes read from the store (those
    whose key is in ``redrawn`` were drawn again after damage, so not cached)."""
    figures = []
    for stage in stages:
        for item in results.get(stage, []):
            if item.get("error"):
                figures.append(Figure(stage, item["name"], "", b"", False, item["seconds"], item["error"]))
                continue
            view = session.store.open(item["key"])
            figures.append(
                Figure(
                    stage,
                    item["name"],
                    view.meta["media"],
                    view.bytes("data"),
                    item["cached"] and item["key"] not in redrawn,
                    item["seconds"],
                )
            )
    return figures


def _slim(record: dict[str, Any]) -> dict[str, Any]:
    """What a figure worker needs of the run record (not the tracebacks and key parts)."""
    return {
        "stages": {n: {k: s.get(k) for k in ("uses", "key", "inputs", "state")} for n, s in record["stages"].items()}
    }


# ---------------------------------------------------------------------------------------------------------- DAG svg
_BOX_W, _BOX_H, _GAP_X, _GAP_Y = 128, 44, 40, 16  # a stage box in the graph and the space between boxes


def dag_svg(pipeline: Pipeline, record: dict[str, Any]) -> str:
    """The stage graph as inline SVG: columns by dependency depth, boxes coloured by state, times inside."""
    from msflow.spec import topological_order

    order = topological_order(pipeline.stages)
    columns = _dag_columns(pipeline, order)
    pos = {}
    for col, names in columns.items():
        for row, name in enumerate(names):
            pos[name] = (20 + col * (_BOX_W + _GAP_X), 20 + row * (_BOX_H + _GAP_Y))
    width = 40 + len(columns) * (_BOX_W + _GAP_X)
    height = 40 + max(len(v) for v in columns.values()) * (_BOX_H + _GAP_Y)
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" style="max-width:100%;height:auto" role="img" '
        f'aria-label="stage graph">',
        '<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="7" markerHeight="7" '
        'orient="auto"><path d="M0,0 L10,5 L0,10 z" fill="#666"/></marker></defs>',
    ]
    for name in order:
        parts.extend(_dag_edge(pos[dep], pos[name]) for dep in pipeline.stages[name].deps)
    for name in order:
        parts.append(_dag_box(name, pos[name], record["stages"].get(name, {})))
    parts.append("</svg>")
    return "".join(parts)


def _dag_columns(pipeline: Pipeline, order: list[str]) -> dict[int, list[str]]:
    """Stages by dependency depth (column), each column ordered to keep edges short."""
    depth: dict[str, int] = {}
    for name in order:
        deps = pipeline.stages[name].deps
        depth[name] = 1 + max((depth[d] for d in deps), default=-1)
    columns: dict[int, list[str]] = {}
    for name in order:
        columns.setdefault(depth[name], []).append(name)
    row_of = {n: i for col in columns.values() for i, n in enumerate(col)}
    for _ in range(3):  # barycentre ordering: a stage sits near the rows of what it reads, fewer crossings
        for col in sorted(columns)[1:]:
            columns[col].sort(
                key=lambda n: sum(row_of[d] for d in pipeline.stages[n].deps) / max(1, len(pipeline.stages[n].deps))
            )
            row_of.update({n: i for i, n in enumerate(columns[col])})
    return columns


def _dag_edge(source: tuple[int, int], target: tuple[int, int]) -> str:
    """An arrow from the right side of one box to the left side of another, as an S curve."""
    x1, y1 = source
    x2, y2 = target
    sx, sy, ex, ey = x1 + _BOX_W, y1 + _BOX_H / 2, x2, y2 + _BOX_H / 2
    mid = (sx + ex) / 2
    return (
        f'<path d="M{sx},{sy} C{mid},{sy} {mid},{ey} {ex},{ey}" fill="none" stroke="#888" '
        f'stroke-width="1.2" marker-end="url(#arrow)"/>'
    )


def _dag_box(name: str, corner: tuple[int, int], entry: dict[str, Any]) -> str:
    """A stage's box: its name, and its time if it ran or failed, else its state; coloured by state."""
    x, y = corner
    state = entry.get("state", StageStatus.PENDING)
    seconds = entry.get("seconds") or 0.0
    timing = f"{seconds:.2f}s" if state in (StageStatus.RAN, StageStatus.FAILED) else state
    return (
        f"<g><title>{html.escape(name)}: {html.escape(state)}</title>"
        f'<rect x="{x}" y="{y}" width="{_BOX_W}" height="{_BOX_H}" rx="7" '
        f'fill="{STATE_COLOURS.get(state, "#eee")}" stroke="#555"/>'
        f'<text x="{x + _BOX_W / 2}" y="{y + 18}" text-anchor="middle" font-size="13" '
        f'font-family="sans-serif" font-weight="bold">{html.escape(name)}</text>'
        f'<text x="{x + _BOX_W / 2}" y="{y + 34}" text-anchor="middle" font-size="11" '
        f'font-family="sans-serif">{html.escape(timing)}</text></g>'
    )


# ---------------------------------------------------------------------------------------------------------- page
CSS = """
body{font-family:system-ui,sans-serif;margin:0 auto;max-width:1200px;padding:1em 2em;color:#222}
h1{margin-bottom:.2em} h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:13px;margin:.5em 0} td,th{border:1px solid #ddd;padding:3px 7px;
vertical-align:top;text-align:left} th{background:#f4f4f4} code,pre{font-size:12px}
pre{background:#f7f7f7;padding:6px;max-height:16em;overflow:auto;margin:0}
td.params pre{white-space:pre-wrap;overflow-wrap:anywhere}
.state{padding:1px 6px;border-radius:4px} figure{margin:.6em 0 1.2em} figcaption{font-size:13px;color:#555}
img,video{max-width:100%;border:1px solid #ddd} .muted{color:#777;font-size:13px} .legend span{margin-right:1em}
"""


def _state_badge(state: str) -> str:
    return f'<span class="state" style="background:{STATE_COLOURS.get(state, "#eee")}">{html.escape(state)}</span>'


def _cell_html(value: object) -> str:
    from msflow.sweep import format_value

    return html.escape(format_value(value, digits=5))


def _media_html(fig: Figure) -> str:
    caption = f"<figcaption>{html.escape(fig.stage)} · {html.escape(fig.name)}</figcaption>"
    if fig.error:
        return f'<figure><p class="muted">figure failed: {html.escape(fig.error)}</p>{caption}</figure>'
    data = base64.b64encode(fig.data).decode()
    if fig.media.startswith("video/"):
        return f'<figure><video controls preload="auto" src="data:{fig.media};base64,{data}"></video>{caption}</figure>'
    return (
        f'<figure><img alt="{html.escape(fig.stage)} {html.escape(fig.name)}" '
        f'src="data:{fig.media};base64,{data}">{caption}</figure>'
    )


def run_page(session: Session, record: dict[str, Any], figures: list[Figure]) -> str:
    """The report page of one run: header, failures, warnings, the pipeline's summary metrics, stage graph, stage
    table, metrics, figures."""
    pipeline = session.pipeline
    from msflow.spec import topological_order

    order = [s for s in topological_order(pipeline.stages) if s in record["stages"]]
    counts = ", ".join(f"{v} {k}" for k, v in record.get("counts", {}).items() if v)
    rows = _stage_rows(record, order)
    metric_rows = _metric_rows(record, order)
    errors = _failure_items(record, order)
    warnings = _warning_items(record, order)
    sections = _figure_sections(record, order, figures)
    legend = "".join(
        f"<span>{_state_badge(s)}</span>"
        for s in (StageStatus.RAN, StageStatus.CACHED, StageStatus.FAILED, StageStatus.SKIPPED)
    )
    versions = ", ".join(f"{k} {v}" for k, v in sorted(record.get("versions", {}).items()))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>msflow report: {html.escape(pipeline.path.name)}</title>
<style>{CSS}</style></head><body>
<h1>{html.escape(pipeline.path.name)}</h1>
<p class="muted">run {html.escape(record["id"])} · started {html.escape(record.get("started", ""))} ·
{record.get("seconds", 0):.2f}s · {html.escape(counts)} · executor {html.escape(str(record.get("executor")))}</p>
{"<h2>Failures</h2><ul>" + "".join(errors) + "</ul>" if errors else ""}
{'<h2>Warnings</h2><ul class="warn">' + "".join(warnings) + "</ul>" if warnings else ""}
{_summary_table(pipeline.summary, record)}
<h2>Stage graph</h2><p class="legend">{legend}</p>{dag_svg(pipeline, record)}
<h2>Stages, params and keys</h2>
<table><tr><th>stage</th><th>state</th><th>time</th><th>key</th><th>params</th></tr>{"".join(rows)}</table>
<h2>Metrics</h2><table><tr><th>stage</th><th>metric</th><th>value</th></tr>{"".join(metric_rows)}</table>
<h2>Figures</h2>{"".join(sections) or '<p class="muted">no figures</p>'}
<h2>Environment</h2><p class="muted">{html.escape(versions)}</p>
</body></html>
"""


def _summary_table(patterns: tuple[str, ...], record: dict[str, Any]) -> str:
    """The pipeline's ``summary:`` metrics first (what ``msflow run`` ends with), or nothing without one."""
    from msflow.summary import format_metric, summary_entries

    entries, _ = summary_entries(list(patterns), record["stages"])
    rows = "".join(
        f"<tr><td>{html.escape(name)}</td><td>{html.escape(format_metric(value))}</td></tr>" for name, value in entries
    )
    return f"<h2>Summary</h2><table><tr><th>metric</th><th>value</th></tr>{rows}</table>" if entries else ""


def _stage_rows(record: dict[str, Any], order: list[str]) -> list[str]:
    """Table rows of the stages: name and class, state, time, key (abbreviated) and resolved params."""
    rows = []
    for name in order:
        entry = record["stages"][name]
        params = "\n".join(
            f"{k}: {json.dumps(v)}" for k, v in (record["config"].get(name) or {}).get("params", {}).items()
        )
        rows.append(
            f"<tr><td><b>{html.escape(name)}</b><br><span class='muted'>{html.escape(entry['uses'])}"
            f"</span></td><td>{_state_badge(entry['state'])}</td><td>{entry.get('seconds', 0):.2f}s</td>"
            f"<td><code>{html.escape(str(entry.get('key') or '')[:16])}</code></td>"
            f"<td class='params'><pre>{html.escape(params)}</pre></td></tr>"
        )
    return rows


def _metric_rows(record: dict[str, Any], order: list[str]) -> list[str]:
    """Table rows of every stage's metrics, one metric a row."""
    metric_rows = []
    for name in order:
        for metric, value in (record["stages"][name].get("metrics") or {}).items():
            metric_rows.append(
                f"<tr><td>{html.escape(name)}</td><td>{html.escape(metric)}</td><td>{_cell_html(value)}</td></tr>"
            )
    return metric_rows


def _failure_items(record: dict[str, Any], order: list[str]) -> list[str]:
    """List items of the failed stages and their errors."""
    return [
        f"<li><b>{html.escape(n)}</b>: {html.escape(str(record['stages'][n].get('error')))}</li>"
        for n in order
        if record["stages"][n]["state"] == StageStatus.FAILED
    ]


def _warning_items(record: dict[str, Any], order: list[str]) -> list[str]:
    """List items of the stages' warnings, one warning an item."""
    return [
        f"<li><b>{html.escape(n)}</b>: {html.escape(w)}</li>"
        for n in order
        for w in record["stages"][n].get("warnings") or []
    ]


def _figure_sections(record: dict[str, Any], order: list[str], figures: list[Figure]) -> list[str]:
    """One section per stage with figures: a heading (stage and class), then its figures."""
    by_stage: dict[str, list[Figure]] = {}
    for fig in figures:
        by_stage.setdefault(fig.stage, []).append(fig)
    sections = []
    for name in order:
        if name in by_stage:
            entry = record["stages"][name]
            sections.append(
                f"<h3 id='stage-{html.escape(name)}'>{html.escape(name)} "
                f"<span class='muted'>{html.escape(entry['uses'])}</span></h3>"
                + "".join(_media_html(f) for f in by_stage[name])
            )
    return sections


def sweep_page(pipeline_name: str, sweep: dict[str, Any], metric: str | None) -> str:
    """Results table of a sweep and a plot of a chosen metric against each swept parameter."""
    from msflow.sweep import SweepResult, VariantOutcome, format_table, metric_columns, results_rows

    result = SweepResult(
        sweep["id"],
        sweep["pipeline"],
        [VariantOutcome(**v) for v in sweep["variants"]],
        sweep["seconds"],
        sweep["executed"],
        sweep["unique_keys"],
        sweep.get("summary", []),  # sweeps recorded before summary: existed have none
    )
    columns = metric_columns(result, result.summary or None)
    metric = _plotted_metric(result, columns, metric)
    header, rows = results_rows(result, columns)
    table = format_table(header, rows, "md")
    body = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    for row in rows:
        body.append("<tr>" + "".join(f"<td>{_cell_html(c)}</td>" for c in row) + "</tr>")
    body.append("</table>")
    plots = ""
    if metric:
        plots = "".join(
            _media_html(Figure("sweep", f"{metric} vs {p}", "image/png", png, False, 0.0))
            for p, png in metric_plots(result, metric).items()
        )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>msflow sweep report: {html.escape(pipeline_name)}</title>
<style>{CSS}</style></head><body>
<h1>Sweep of {html.escape(pipeline_name)}</h1>
<p class="muted">sweep {html.escape(sweep["id"])} · {len(result.variants)} variants · {result.executed} stage
executions for {result.unique_keys} distinct keys · {result.seconds:.2f}s</p>
<h2>Results</h2>{"".join(body)}
<h2>{html.escape(metric or "no metric")} against each swept parameter</h2>{plots}
<details><summary>Markdown</summary><pre>{html.escape(table)}</pre></details>
</body></html>
"""


def _plotted_metric(result: SweepResult, columns: list[str], asked: str | None) -> str | None:
    """The metric plotted against the swept parameters: the one asked for (UserError naming --metric when the
    sweep has no such metric), else the first column whose value differs between variants, else the first."""
    from msflow.sweep import variant_metric

    if asked is not None:
        known = sorted({f"{stage}.{m}" for v in result.variants for stage, ms in v.metrics.items() for m in ms})
        if asked not in known:
            raise UserError(f"the sweep has no metric '{asked}'; its metrics: {', '.join(known)}", field="--metric")
        return asked
    varying = [c for c in columns if len({json.dumps(variant_metric(v, c)) for v in result.variants if v.ok}) > 1]
    chosen = varying or columns
    return chosen[0] if chosen else None


def metric_plots(result: SweepResult, metric: str) -> dict[str, bytes]:
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from msflow.sweep import variant_metric

    params = list(dict.fromkeys(t for v in result.variants for t in v.params))
    plots: dict[str, bytes] = {}
    for param in params:
        pairs = [(v.params.get(param), variant_metric(v, metric)) for v in result.variants if v.ok]
        points: list[tuple[Any, float]] = [
            (x, float(y)) for x, y in pairs if isinstance(y, (int, float)) and x is not None
        ]
        if not points:
            continue
        fig, ax = plt.subplots(figsize=(5, 3.2))
        numeric = all(isinstance(x, (int, float)) for x, _ in points)
        xs: list[Any] = [x if numeric else str(x) for x, _ in points]
        ax.plot(xs, [y for _, y in points], "o")
        ax.set_xlabel(param)
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=96, bbox_inches="tight")
        plt.close(fig)
        plots[param] = buf.getvalue()
    return plots


# ---------------------------------------------------------------------------------------------------------- entry
def find_record(session: Session, run: str | None) -> dict[str, Any]:
    store = session.store
    if run:
        return store.read_run(run)
    rel = session.pipeline.rel_path
    for run_id in reversed(store.run_ids()):
        try:
            record = store.read_run(run_id)
        except CorruptRecord:  # a damaged record: the newest readable run of the pipeline is reported
            continue
        if record.get("pipeline") == rel and not record.get("sweep") and not record.get("interrupted"):
            return record
    raise UserError("no run of this pipeline yet: run it first (msflow run)", file=str(session.pipeline.path))


def build_report(
    path: str | Path, out: str | Path, run: str | None = None, *, jobs: int = 2, metric: str | None = None
) -> dict[str, Any]:
    """Write the report of a run (default: the newest) or, if ``run`` names a sweep, of that sweep."""
    from msflow.session import open_session

    started = time.perf_counter()
    session = open_session(path)
    with matplotlib_inside(session):
        return _build_report(session, out, run, jobs=jobs, metric=metric, started=started)


@contextmanager
def matplotlib_inside(session: Session) -> Iterator[None]:
    """matplotlib makes its configuration folder and writes its font list into the user's home on first use:
    point it (``MPLCONFIGDIR``, inherited by the figure workers) at the store's local cache folder
    (``Store.local_cache``) instead, unless the user chose one, so a report writes nothing outside the project and
    store."""
    if "MPLCONFIGDIR" in os.environ or session.store.local_cache is None:
        yield
        return
    folder = session.store.local_cache / "matplotlib"
    folder.mkdir(parents=True, exist_ok=True)
    os.environ["MPLCONFIGDIR"] = str(folder)
    try:
        yield
    finally:
        os.environ.pop("MPLCONFIGDIR", None)


def _build_report(
    session: Session, out: str | Path, run: str | None, *, jobs: int, metric: str | None, started: float
) -> dict[str, Any]:
    store = session.store
    if run and any(s == run or s.endswith(run) for s in store.sweep_ids()):
        sweep_id = next(s for s in store.sweep_ids() if s == run or s.endswith(run))
        sweep = store.read_sweep(sweep_id)
        page = sweep_page(session.pipeline.path.name, sweep, metric)
        figures: list[Figure] = []
    else:
        record = find_record(session, run)
        figures = collect_figures(session, record, jobs)
        page = run_page(session, record, figures)
    out = Path(out)
    if out.is_dir():
        raise UserError("is a folder; give the HTML file to write", file=str(out), field="--out")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(out, page)
    except OSError as exc:
        raise UserError(f"cannot write: {exc.strerror or exc}", file=str(out), field="--out") from None
    session.save_memo()
    return {
        "path": str(out),
        "bytes": out.stat().st_size,
        "figures": len(figures),
        "rendered": sum(1 for f in figures if not f.cached and not f.error),
        "failed": [f"{f.stage}.{f.name}: {f.error}" for f in figures if f.error],
        "seconds": time.perf_counter() - started,
    }
