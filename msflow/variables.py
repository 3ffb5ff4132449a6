"""Pipeline variables: the ``${name}`` references, and published names that an override makes untrue.

A pipeline names its published files after variables that also set what is computed: ``pipeline.yaml`` publishes
``out/sad_as_${mood}.glb``, where ``mood`` is ``${mood_from}_to_${mood_to}``, the ends of ``blend.alpha``'s mood
swing. ``-S blend.alpha=from_analysis`` replaces that swing, and the run would write its animation into
``out/sad_as_happy_to_disgust.glb``, silently. msflow knows nothing of moods; it sees that the override took the
variables out of the param they were in, while a ``publish:`` path still uses them, and says so, naming the
variable that renames the files (``-S vars.NAME=...``, which exists for exactly this).
"""

from __future__ import annotations

import re
from typing import Any

from msflow.errors import display_path

#: ``${name}`` or ``${name:filter}`` in a pipeline file (msflow.spec fills them in)
VAR_RE = re.compile(r"\$\{([^}]*)\}")


def var_refs(value: Any) -> set[str]:
    """The variables ``value`` names (``${name}``, ``${name:filter}``), in strings and mapping keys, at any depth."""
    if isinstance(value, str):
        return {m.group(1).partition(":")[0] for m in VAR_RE.finditer(value)}
    if isinstance(value, dict):
        return set().union(set(), *(var_refs(k) | var_refs(v) for k, v in value.items()))
    if isinstance(value, list):
        return set().union(set(), *(var_refs(v) for v in value))
    return set()


def var_closure(names: set[str], variables: dict[str, Any]) -> set[str]:
    """``names`` and every variable their values use, and so on (``mood`` -> ``mood_from``, ``mood_to``)."""
    seen: set[str] = set()
    stack = list(names)
    while stack:
        name = stack.pop()
        if name not in seen:
            seen.add(name)
            stack.extend(var_refs(variables.get(name)))
    return seen


def param_at(raw: dict[str, Any], stage: str, path: list[str]) -> Any:
    """The value the pipeline file gives ``stage``'s param at ``path`` (None when it gives none)."""
    value: Any = (raw.get("stages") or {}).get(stage)
    for key in ["params", *path]:
        if not isinstance(value, dict):
            return None
        value = value.get(key)
    return value


def untrue_names(
    before: dict[str, Any],
    after: dict[str, Any],
    overrides: list[tuple[list[str], Any]],
    publish: dict[str, str],
) -> list[str]:
    """A warning per param that ``-S stage.param=value`` overrides took variables out of while ``publish:`` paths
    still use them. ``before``/``after``: the pipeline as written / with the overrides applied, variables not yet
    filled in; ``overrides``: (path, value) as parsed; ``publish``: entry -> the file it writes. What the overrides
    leave in the param counts (a later ``-S`` may put the variable back), and a variable the command line sets
    (``-S vars.NAME=...``) is named by the user: the files say what the user said."""
    vars_before, vars_after = before.get("vars") or {}, after.get("vars") or {}
    named_here = {parts[1] for parts, _ in overrides if parts[0] == "vars"}
    entries = after.get("publish") or {}
    messages = []
    for parts in dict.fromkeys(tuple(parts) for parts, _ in overrides if parts[0] != "vars"):
        had = var_closure(var_refs(param_at(before, parts[0], list(parts[1:]))), vars_before)
        left = var_closure(var_refs(param_at(after, parts[0], list(parts[1:]))), vars_after)
        dropped = had - left - named_here
        naming = {ref: dropped & var_closure(var_refs(path), vars_after) for ref, path in entries.items()}
        named = {ref: path for ref, path in entries.items() if naming[ref]}
        if named:
            lost = set().union(*(naming[ref] for ref in named))
            messages.append(_message(".".join(parts), lost, named, publish, vars_after))
    return messages


def _message(
    target: str, lost: set[str], named: dict[str, Any], publish: dict[str, str], variables: dict[str, Any]
) -> str:
    """``-S blend.alpha no longer uses ${mood_from}, ...``: the files, and the variables that rename them (those
    the paths name, through which they use the lost ones)."""
    used = sorted({v for path in named.values() for v in var_refs(path) if var_closure({v}, variables) & lost})
    through = [v for v in used if v not in lost]
    files = ", ".join(display_path(publish[ref]) for ref in named if ref in publish)
    return (
        f"-S {target} no longer uses {_listed(lost)}, which the published files are named after"
        f"{f' (through {_listed(through)})' if through else ''}: {files} will hold the override's result under "
        f"names that no longer say what it is; name them for it with {' '.join(f'-S vars.{v}=...' for v in used)}"
    )


def _listed(names: Any) -> str:
    return ", ".join(f"${{{v}}}" for v in sorted(names))
