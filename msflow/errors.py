"""Errors msflow distinguishes: a user's mistake (exit 2) versus a failing stage (exit 1)."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
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
        for named in (f"stage '{stage}', ", f"stage '{stage}': "):  # a result check names the stage itself
            message = message.removeprefix(named)
        super().__init__(f"stage '{stage}' failed: {message}")
        self.stage = stage
        self.message = message
        self.traceback = traceback


class CorruptArtifact(Exception):
    """A stored artifact failed an integrity check on read: a chunk whose checksum does not match, a missing chunk,
    an unreadable manifest. Exit code 1. ``msflow run`` moves such an artifact aside and recomputes it."""

    exit_code = 1

    def __init__(self, key: str | None, problem: str, stage: str | None = None):
        super().__init__(problem)
        self.key = key
        self.problem = problem
        self.stage = stage

    def located(self, *, stage: str | None = None) -> CorruptArtifact:
        self.stage = self.stage or stage
        return self

    def __str__(self) -> str:
        what = f"the artifact {self.key}" if self.key else "an artifact"
        if self.stage:
            what += f" of stage '{self.stage}'"
        return (
            f"{what} is corrupt: {self.problem}. `msflow verify` lists corrupt artifacts; `msflow run` moves an "
            "artifact it finds corrupt aside and recomputes it (or remove them all: `msflow verify --delete`)"
        )


class CorruptRecord(CorruptArtifact):
    """A run or sweep record that is not a JSON object (damaged, or edited by hand). Only the history is hurt: the
    artifacts are checked on their own, and ``msflow runs`` and ``msflow report`` pass over such a run record."""

    def __str__(self) -> str:
        return f"{self.problem}; the artifacts do not depend on it: delete the file to drop it from the history"


#: what reading a damaged artifact raises (zarr's checksum and decoding errors, a missing chunk); anything else
#: (a network failure, a UserError naming the store) is not corruption
READ_DAMAGE = (ValueError, RuntimeError, FileNotFoundError, EOFError, KeyError)


class InvalidResult(TypeError, ValueError):
    """What a stage's ``run`` returned breaks its declared outputs or the strict-JSON rules (a bug in the stage).

    A ``TypeError`` and a ``ValueError`` both, as the schema checks raise either; the runner reports it as a
    failed stage without a traceback (the message names the stage and output)."""


def display_path(path: str | os.PathLike[str], start: str | os.PathLike[str] | None = None, ups: int = 0) -> str:
    """A path as messages show it: relative to the current folder (or ``start``) when inside it, or at most
    ``ups`` folders above it (``../eval/face.yaml``), else absolute: a climb of several '..' is hard to read.

    >>> display_path(os.path.join(os.getcwd(), "pipeline.yaml"))
    'pipeline.yaml'
    """
    text = os.fspath(path)
    if "://" in text:
        return text
    absolute = os.path.abspath(text)
    try:
        relative = os.path.relpath(absolute, start)
    except ValueError:  # another drive
        return absolute
    return absolute if relative.split(os.sep).count("..") > ups else relative


#: the member tags pydantic puts into error locations of union-typed fields: "int", "literal['a','b']",
#: "function-after[...]", "list[float]" ... (a user's field is never named like these)
PYDANTIC_TAG = re.compile(
    r"^(?:int|float|str|bool|bytes|none|list|dict|tuple|set|frozenset|decimal|date|datetime|time|timedelta|"
    r"uuid|url|path|json-or-python|[a-z][a-z0-9_-]*\[.*\])$"
)


def field_path(loc: Sequence[object]) -> str:
    """A pydantic error location as a dotted field path, without pydantic's union member tags.

    >>> field_path(("k", "int"))
    'k'
    >>> field_path(("alpha", "literal['a','b']", "keyframes", 0))
    'alpha.keyframes.0'
    >>> field_path(("time", "float"))  # the first part always names a field, whatever it is called
    'time'
    """
    return ".".join(strip_tags(loc))


def strip_tags(loc: Sequence[object]) -> list[str]:
    """The parts of a pydantic error location that name fields, keys and indices (union member tags dropped; the
    first part is the field of the model itself, never a tag)."""
    return [str(p) for i, p in enumerate(loc) if not (i and isinstance(p, str) and PYDANTIC_TAG.match(p))]


class StoreInUse(UserError):
    """``msflow gc`` found runs using the store: it would delete the artifacts they are making."""
