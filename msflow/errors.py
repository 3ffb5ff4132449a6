"""Errors msflow distinguishes: a user's mistake (exit 2) versus a failing stage (exit 1)."""

from __future__ import annotations

import os
from typing import Any


class UserError(Exception):
    """Something the user can fix: bad config, missing file, unusable data.

    The CLI prints it without a traceback and exits with code 2. ``file``, ``stage`` and ``field`` locate
    the problem; stages raise it (``raise UserError("no face found", field="inputs.videos.sad")``) and the
    runner fills in the stage name.
    """

    exit_code = 2

    def __init__(self, message: str, *, file: str | None = None, stage: str | None = None, field: str | None = None):
        super().__init__(message)
        self.message = message
        self.file = file
        self.stage = stage
        self.field = field

    def located(self, *, file: str | None = None, stage: str | None = None, field: str | None = None) -> UserError:
        """Fill in location parts that are still unknown; returns self."""
        self.file = self.file or file
        self.stage = self.stage or stage
        self.field = self.field or field
        return self

    def __str__(self) -> str:
        where = []
        if self.file:
            where.append(display_path(self.file))
        if self.stage:
            where.append(f"stage '{self.stage}'")
        if self.field:
            where.append(f"field '{self.field}'")
        return (": ".join(where) + ": " if where else "") + self.message

    def to_json(self) -> dict[str, Any]:
        return {
            "type": "UserError",
            "message": self.message,
            "file": self.file,
            "stage": self.stage,
            "field": self.field,
        }


class StageFailed(Exception):
    """A stage raised something other than UserError (a bug or an environment problem): exit 1."""

    exit_code = 1

    def __init__(self, stage: str, message: str, traceback: str = ""):
        super().__init__(f"stage '{stage}' failed: {message}")
        self.stage = stage
        self.message = message
        self.traceback = traceback


class InvalidResult(TypeError, ValueError):
    """What a stage's ``run`` returned breaks its declared outputs or the strict-JSON rules (a bug in the stage).

    A ``TypeError`` and a ``ValueError`` both, as the schema checks raise either; the runner reports it as a
    failed stage without a traceback (the message names the stage and output)."""


def display_path(path: str | os.PathLike[str]) -> str:
    """A path as messages show it: relative to the current folder when inside it, else absolute.

    >>> display_path(os.path.join(os.getcwd(), "pipeline.yaml"))
    'pipeline.yaml'
    """
    text = os.fspath(path)
    if "://" in text:
        return text
    absolute = os.path.abspath(text)
    try:
        relative = os.path.relpath(absolute)
    except ValueError:  # another drive
        return absolute
    return absolute if relative.startswith("..") else relative
