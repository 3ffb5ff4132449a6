"""The keymorph YAML an artist edits (paper Sec 4.3): ``expression -> keyshape id -> {morph target: weight}``.

``format_keymorph_yaml`` writes it (one keyshape per line, zeros left out), ``parse_keymorph_yaml`` reads it back,
every mistake a ``UserError`` naming the file, the line and the valid choices.
"""

from __future__ import annotations

import difflib
import re

import numpy as np

from msflow import UserError

_PLAIN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_YAML_WORDS = {"true", "false", "yes", "no", "on", "off", "null", "y", "n", "~"}
#: the pipeline field of the keymorph file, named in its UserErrors
_FIELD = "inputs.keymorphs"


def _yaml_key(name: str) -> str:
    if _PLAIN.match(name) and name.lower() not in _YAML_WORDS:
        return name
    return "'" + name.replace("'", "''") + "'"


def format_keymorph_yaml(
    labels: list[str],
    keyshape_expression: np.ndarray,
    keyshape_index: np.ndarray,
    weights: np.ndarray,
    names: list[str],
    *,
    comments: list[str] | None = None,
    header: str = "",
    decimals: int | None = 3,
) -> str:
    """The keymorph YAML: ``expression -> keyshape id -> {morph target: weight}``, one keyshape per line.

    Weights are rounded to ``decimals`` (None: written exactly) and zeros left out, so the file stays short
    enough to edit by hand. ``comments`` (one per keyshape) go at the end of each line.
    """
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    for s, label in enumerate(labels):
        mine = np.flatnonzero(np.asarray(keyshape_expression) == s)
        lines.append(f"{_yaml_key(label)}:" + ("  {}" if not mine.size else ""))
        for k in mine:
            w = np.asarray(weights[k], np.float64)
            if decimals is not None:
                w = np.round(w, decimals)
            items = ", ".join(f"{_yaml_key(names[m])}: {_number(w[m], decimals)}" for m in np.flatnonzero(w > 0))
            note = f"  # {comments[k]}" if comments else ""
            lines.append(f"  {int(keyshape_index[k])}: {{{items}}}{note}")
    return "\n".join(lines) + "\n"


def _number(value: float, decimals: int | None) -> str:
    if decimals is None:
        return repr(float(value))
    return f"{value:.{decimals}f}".rstrip("0").rstrip(".")


def rounded_weights(weights: np.ndarray, decimals: int = 3) -> np.ndarray:
    """The weights exactly as ``format_keymorph_yaml`` writes them."""
    return np.clip(np.round(np.asarray(weights, np.float64), decimals), 0.0, 1.0)


def _suggest(name: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(name, valid, n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def parse_keymorph_yaml(
    text: str, labels: list[str], counts: list[int], names: list[str], *, file: str, allow_missing: bool = False
) -> np.ndarray:
    """Keymorph weights (total_k, M) from the YAML text; every mistake is a UserError naming the valid choices.

    Keyshape ids are each expression's own ids 0..k_s-1 (``keyshape_index`` of the keyshapes artifact), the
    rows come out in the keyshapes artifact's order (grouped by expression).
    """
    data = _load_top_mapping(text, file)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    weights = np.zeros((int(offsets[-1]), len(names)))
    seen = np.zeros(int(offsets[-1]), dtype=bool)
    index = {name: m for m, name in enumerate(names)}
    for expression, keymorphs in data.items():
        expression = str(expression)
        s = _expression_index(expression, labels, file)
        for key, morphs in _keyshape_mapping(expression, keymorphs, counts[s], file).items():
            local = _keyshape_id(expression, key, counts[s], file)
            row = offsets[s] + local
            if seen[row]:
                raise UserError(f"{expression}: keyshape id {local} is given twice", file=file, field=_FIELD)
            seen[row] = True
            _read_morph_weights(weights[row], f"{expression}/{local}", morphs, index, names, file)
    if not allow_missing and not seen.all():
        raise UserError(
            f"keymorph file has no entry for keyshapes {_missing_keyshapes(labels, counts, offsets, seen)} (an "
            "empty {} means the neutral face; or set allow_missing to treat missing ones as neutral)",
            file=file,
            field=_FIELD,
        )
    return weights


def _load_top_mapping(text: str, file: str) -> dict:
    """The YAML's top level, ``expression -> keyshapes``: an empty file is an empty mapping."""
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise UserError(f"keymorph file is not valid YAML: {exc}", file=file, field=_FIELD) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise UserError(
            "keymorph file must map expression names to keyshape ids to {morph target: weight}, "
            f"found a {type(data).__name__} at the top level",
            file=file,
            field=_FIELD,
        )
    return data


def _expression_index(expression: str, labels: list[str], file: str) -> int:
    """The expression's position among the keyshapes' labels."""
    if expression not in labels:
        raise UserError(
            f"unknown expression '{expression}'{_suggest(expression, labels)}; the keyshapes have "
            f"expressions: {', '.join(labels)}",
            file=file,
            field=_FIELD,
        )
    return labels.index(expression)


def _keyshape_mapping(expression: str, keymorphs: object, count: int, file: str) -> dict:
    """One expression's ``keyshape id -> morphs``: an empty entry (``happy:``) is an empty mapping."""
    if keymorphs is None:
        keymorphs = {}
    if not isinstance(keymorphs, dict):
        raise UserError(
            f"'{expression}' must map keyshape ids (0..{count - 1}) to {{morph target: weight}}",
            file=file,
            field=_FIELD,
        )
    return keymorphs


def _keyshape_id(expression: str, key: object, count: int, file: str) -> int:
    """The expression's own keyshape id 0..count-1 from a YAML key: an int or a quoted digit string (not a bool)."""
    local = (
        int(key)
        if isinstance(key, int) and not isinstance(key, bool)
        else int(key)
        if isinstance(key, str) and key.strip().isdigit()
        else -1
    )
    if not 0 <= local < count:
        raise UserError(
            f"{expression}: unknown keyshape id '{key}'; valid ids for '{expression}' are 0..{count - 1}",
            file=file,
            field=_FIELD,
        )
    return local


def _read_morph_weights(
    row: np.ndarray, where: str, morphs: object, index: dict[str, int], names: list[str], file: str
) -> None:
    """Write one keyshape's ``{morph target: weight}`` into its row of weights; ``where`` is ``expression/id``."""
    if morphs is None:
        morphs = {}
    if not isinstance(morphs, dict):
        raise UserError(
            f"{where}: expected {{morph target: weight}}, found {type(morphs).__name__}", file=file, field=_FIELD
        )
    for name, value in morphs.items():
        name = str(name)
        if name not in index:
            raise UserError(
                f"{where}: unknown morph target '{name}'{_suggest(name, names)}; "
                f"the character's targets are: {', '.join(names)}",
                file=file,
                field=_FIELD,
            )
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise UserError(f"{where}: weight of '{name}' must be a number, got {value!r}", file=file, field=_FIELD)
        if not 0.0 <= value <= 1.0:
            raise UserError(f"{where}: weight of '{name}' is {value}, outside [0, 1]", file=file, field=_FIELD)
        row[index[name]] = float(value)


def _missing_keyshapes(labels: list[str], counts: list[int], offsets: np.ndarray, seen: np.ndarray) -> dict:
    """``expression -> keyshape ids`` the file has no entry for (expressions with none missing left out)."""
    missing = {}
    for s, label in enumerate(labels):
        ids = [i for i in range(counts[s]) if not seen[offsets[s] + i]]
        if ids:
            missing[label] = ids
    return missing
