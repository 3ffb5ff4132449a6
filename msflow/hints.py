"""Hints naming another file of the project: the pipeline file the user probably meant (``msflow run capture.yaml``
typed for ``pipelines/capture.yaml``, ``-S vars.take=...`` given to a pipeline without ``take``).

Pipeline files live in the project root or one folder down (``pipelines/``, ``eval/``); only those places are
looked at, so a hint costs a few directory listings, and only when there already is an error to report.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from msflow.errors import display_path

#: YAML files larger than this are data, not pipelines: not parsed for a hint
MAX_PIPELINE_BYTES = 1_000_000


def _pipeline_folders(root: Path) -> list[Path]:
    """The project root and its first-level folders, hidden ones (.git, .msflow) left out."""
    try:
        below = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    except OSError:
        return [root]
    return [root, *below]


def same_name_in_project(name: str, root: Path, missing: Path) -> str:
    """A hint naming the project's files called ``name`` (the file ``missing`` was not found), or ""."""
    found = [
        folder / name
        for folder in _pipeline_folders(root)
        if (folder / name).is_file() and (folder / name).resolve() != missing.resolve()
    ]
    if not found:
        return ""
    return f"; did you mean {' or '.join(display_path(p, ups=1) for p in found)}? (give it as the FILE argument)"


def _declared_vars(path: Path) -> dict[Any, Any]:
    """The ``vars:`` of a pipeline file; {} for a file that is not one (or cannot be read)."""
    import yaml

    try:
        if path.stat().st_size > MAX_PIPELINE_BYTES:
            return {}
        raw = yaml.load(path.read_text(encoding="utf-8"), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except (OSError, ValueError, yaml.YAMLError):
        return {}
    if not (isinstance(raw, dict) and isinstance(raw.get("stages"), dict) and isinstance(raw.get("vars"), dict)):
        return {}
    declared: dict[Any, Any] = raw["vars"]
    return declared


def pipelines_with_variable(variable: str, root: Path, pipeline: Path) -> str:
    """A hint naming the project's other pipeline files that declare ``variable`` in ``vars:``, or ""."""
    found = [
        path
        for folder in _pipeline_folders(root)
        for path in sorted([*folder.glob("*.yaml"), *folder.glob("*.yml")])
        if path.resolve() != pipeline.resolve() and variable in _declared_vars(path)
    ]
    if not found:
        return ""
    files = ", ".join(display_path(p, ups=1) for p in found)
    return f"; {files} {'has' if len(found) == 1 else 'have'} '{variable}' (the pipeline file you meant?)"
