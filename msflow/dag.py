"""Rendering the stage graph: plain text, Mermaid and Graphviz dot (optionally coloured by stage state)."""

from __future__ import annotations

from msflow.jobs import DryStatus, StageStatus
from msflow.spec import FilesRef, Pipeline, StageRef, topological_order

#: fill colours by stage status (runs) and dry status (msflow status); looked up with plain strings from records too
STATE_COLOURS: dict[str, str] = {
    StageStatus.PENDING: "#eeeeee",
    StageStatus.CACHED: "#9ecae1",
    StageStatus.RAN: "#74c476",
    StageStatus.FAILED: "#fb6a4a",
    StageStatus.SKIPPED: "#d9d9d9",
    DryStatus.RUN: "#fdd49e",
    DryStatus.BLOCKED: "#fdd49e",
}


def edges(pipeline: Pipeline) -> list[tuple[str, str, str]]:
    """(upstream, downstream, label) for every stage-to-stage input."""
    out = []
    for name in topological_order(pipeline.stages):
        for input_name, ref in pipeline.stages[name].inputs.items():
            if isinstance(ref, StageRef):
                label = input_name if ref.output is None else f"{ref.output} → {input_name}"
                out.append((ref.stage, name, label))
    return out


def render_text(pipeline: Pipeline, states: dict[str, str] | None = None) -> str:
    lines = []
    width = max(len(n) for n in pipeline.stages)
    for name in topological_order(pipeline.stages):
        node = pipeline.stages[name]
        sources = []
        for input_name, ref in node.inputs.items():
            if isinstance(ref, StageRef):
                sources.append(f"{input_name}←{ref.describe()}")
            elif isinstance(ref, FilesRef):
                sources.append(f"{input_name}←{len(ref.files)} file{'s' if len(ref.files) != 1 else ''}")
        state = f"  [{states[name]}]" if states and name in states else ""
        lines.append(f"{name:<{width}}  {node.uses}{state}")
        if sources:
            lines.append(f"{'':<{width}}    {'  '.join(sources)}")
    return "\n".join(lines)


def _mermaid_id(name: str) -> str:
    return "s_" + "".join(c if c.isalnum() else "_" for c in name)


def render_mermaid(pipeline: Pipeline, states: dict[str, str] | None = None) -> str:
    lines = ["graph TD"]
    for name in topological_order(pipeline.stages):
        cls = pipeline.stages[name].uses.rpartition(":")[2]
        lines.append(f'    {_mermaid_id(name)}["{name}<br/><small>{cls}</small>"]')
    for up, down, label in edges(pipeline):
        lines.append(f"    {_mermaid_id(up)} -->|{label}| {_mermaid_id(down)}")
    if states:
        for state, colour in STATE_COLOURS.items():
            members = [_mermaid_id(n) for n, s in states.items() if s == state]
            if members:
                lines.append(f"    classDef {state} fill:{colour}")
                lines.append(f"    class {','.join(members)} {state}")
    return "\n".join(lines)


def render_dot(pipeline: Pipeline, states: dict[str, str] | None = None) -> str:
    lines = ["digraph pipeline {", "  rankdir=TB;", '  node [shape=box, style="rounded,filled", fillcolor="#ffffff"];']
    for name in topological_order(pipeline.stages):
        cls = pipeline.stages[name].uses.rpartition(":")[2]
        colour = STATE_COLOURS.get((states or {}).get(name, ""), "#ffffff")
        lines.append(f'  "{name}" [label="{name}\\n{cls}", fillcolor="{colour}"];')
    for up, down, label in edges(pipeline):
        lines.append(f'  "{up}" -> "{down}" [label="{label}"];')
    lines.append("}")
    return "\n".join(lines)
