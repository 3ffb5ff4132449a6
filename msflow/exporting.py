"""Writing an artifact's outputs to files (``msflow export``, ``publish:``): one output as .npy, .npz, .csv, .json,
or the raw bytes of a file output (GLB, MP4, CSV ... produced by a stage); all of a stage's arrays as one .npz."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from msflow.atomic import write_with
from msflow.errors import CorruptArtifact, UserError, display_path
from msflow.sinks import iter_blocks

if TYPE_CHECKING:
    from msflow.artifact import ArtifactView
    from msflow.publishers import Publication
    from msflow.runner import StageState
    from msflow.session import Session

ARRAY_SUFFIXES = (".npy", ".npz", ".csv", ".json")


def export_output(view: ArtifactView, output: str, dest: Path, *, field: str = "FILE") -> None:
    """Write one output of an artifact to ``dest`` atomically, in the format its suffix names (a file output:
    its own bytes, streamed chunk by chunk). ``field`` names the setting that chose ``dest`` in error messages."""
    if output not in view:
        raise UserError(f"no output '{output}'; outputs: {', '.join(view.names)}", field="STAGE.output")
    dest = Path(dest)
    refuse_folder(dest, field)
    write_export(dest, output_writer(view, output, dest, field), field)


def export_outputs(view: ArtifactView, stage: str, dest: Path) -> list[str]:
    """``msflow export STAGE FILE``: write the stage's only output to ``dest`` in the format its suffix names, or
    all of its outputs into one .npz (one array each, named as the outputs); returns the outputs written. Any
    other file for a stage of several outputs is an error that lists them and shows ``STAGE.OUTPUT``."""
    import numpy as np

    dest = Path(dest)
    if len(view.names) == 1:
        export_output(view, view.names[0], dest)
        return list(view.names)
    files = [n for n in view.names if view.manifest.get("outputs", {}).get(n, {}).get("file_suffix")]
    if dest.suffix.lower() != ".npz" or files:
        raise UserError(several_outputs(view, stage, files), field="STAGE.output")
    refuse_folder(dest, "FILE")
    write_export(dest, lambda fh: np.savez_compressed(fh, **{n: view[n] for n in view.names}), "FILE")
    return list(view.names)


def several_outputs(view: ArtifactView, stage: str, files: list[str]) -> str:
    """The error for ``msflow export STAGE FILE`` naming no output of a stage that has several (``files``: those
    that are file outputs, GLB or MP4 bytes of their own format, which a .npz cannot hold)."""
    has = f"stage '{stage}' has {len(view.names)} outputs ({', '.join(view.names)})"
    name_one = f"write STAGE.OUTPUT (e.g. {stage}.{view.names[0]})"
    if files:
        return f"{has}, file outputs among them ({', '.join(files)}): {name_one}"
    return f"{has}: {name_one}, or give a .npz file to hold them all"


def refuse_folder(dest: Path, field: str) -> None:
    if dest.is_dir():
        raise UserError("is a folder; give the file to write", file=display_path(dest), field=field)


def write_export(dest: Path, writer: Callable[[IO[bytes]], object], field: str) -> None:
    """Fill ``dest`` with ``writer`` atomically, its folder made; a file system's refusal is the user's to fix."""
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        write_with(dest, writer)
    except OSError as exc:
        raise UserError(f"cannot write: {exc.strerror or exc}", file=display_path(dest), field=field) from None


def output_writer(view: ArtifactView, output: str, dest: Path, field: str) -> Callable[[IO[bytes]], object]:
    """A function writing ``output`` to a binary file in the format ``dest``'s suffix names."""
    import numpy as np

    entry = view.manifest.get("outputs", {}).get(output, {})
    suffix = dest.suffix.lower()
    if entry.get("file_suffix"):

        def write_bytes(fh: IO[bytes]) -> None:
            lazy = view.lazy(output)
            for block in iter_blocks(lazy) if lazy.shape[0] else ():
                fh.write(np.ascontiguousarray(block).tobytes())

        return write_bytes
    if suffix not in ARRAY_SUFFIXES:
        raise UserError(
            f"unsupported export format '{suffix or dest.name}'; use one of {', '.join(ARRAY_SUFFIXES)}",
            file=display_path(dest),
            field=field,
        )
    arr = view[output]
    if suffix == ".npy":
        return lambda fh: np.save(fh, arr, allow_pickle=False)
    if suffix == ".npz":
        return lambda fh: np.savez_compressed(fh, **{output: arr})
    if suffix == ".csv":
        return lambda fh: fh.write(array_to_csv(arr, output).encode("utf-8"))
    data = np.where(np.isfinite(arr), arr, np.nan).tolist() if arr.dtype.kind == "f" else arr.tolist()
    text = json.dumps({"name": output, "shape": list(arr.shape), "dtype": str(arr.dtype), "data": _nan_to_none(data)})
    return lambda fh: fh.write(text.encode("utf-8"))


def array_to_csv(arr: Any, name: str) -> str:
    """Rows = first axis; the remaining axes are flattened into columns named name[i][j]..."""
    import io

    import numpy as np

    arr = np.asarray(arr)
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)
    elif arr.ndim == 1:
        arr = arr.reshape(-1, 1)
    rows = arr.reshape(arr.shape[0], -1)
    cols = [name + "".join(f"[{i}]" for i in idx) for idx in np.ndindex(*arr.shape[1:])] if arr.ndim > 1 else [name]
    if arr.ndim == 2 and arr.shape[1] == 1:
        cols = [name]
    buf = io.StringIO()
    buf.write(",".join(cols) + "\n")
    fmt = "%.9g" if rows.dtype.kind == "f" else "%d"
    np.savetxt(buf, rows.astype(np.int64) if rows.dtype.kind == "b" else rows, delimiter=",", fmt=fmt)
    return buf.getvalue()


def _nan_to_none(value: Any) -> Any:
    if isinstance(value, list):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, float) and value != value:
        return None
    return value


def publish_outputs(session: Session, states: dict[str, StageState]) -> Publication:
    """Materialise the pipeline's ``publish:`` entries; skip files already holding the same output content;
    remember who published each file (msflow.publishers) and warn when that replaces another's."""
    from msflow.hashing import stat_signature
    from msflow.publishers import Publication, PublisherLedger

    published = session.memo.setdefault("published", {})
    ledger = PublisherLedger(session)
    done = Publication()
    try:
        for ref, dest in session.pipeline.publish.items():
            stage = ref.partition(".")[0]
            state = states.get(stage)
            if state is None or not state.state.done:
                continue
            digest = _output_digest(session, state, ref)
            done.files.append(dest)
            if _holds(published.get(dest), digest, dest):  # what this run would write: nothing replaced
                ledger.claim(dest, ref, replaced=False)
                continue
            replaced = os.path.exists(dest)
            _publish_one(session, state, ref, Path(dest))
            done.written.append(dest)
            published[dest] = [digest, stat_signature(Path(dest))]
            warning = ledger.claim(dest, ref, replaced)
            if warning:
                done.warnings.append(warning)
    finally:  # the files written before a failure were published all the same
        ledger.save()
    return done


def _holds(previous: list[str] | None, digest: str, dest: str) -> bool:
    """Whether ``dest`` still holds the output of content hash ``digest``, as published before (``previous``:
    the hash and the file's stat signature then, from the memo)."""
    from msflow.hashing import stat_signature

    if not previous or previous[0] != digest or not os.path.exists(dest):
        return False
    return bool(previous[1] == stat_signature(Path(dest)))


def _output_digest(session: Session, state: StageState, ref: str) -> str:
    """The content hash of the output ``ref`` (``stage.output``) names, from its stage's manifest."""
    stage, _, output = ref.partition(".")
    digest = (state.manifest or {}).get("outputs", {}).get(output, {}).get("hash")
    if digest is None:
        raise UserError(
            f"stage '{stage}' has no output '{output}'", file=str(session.pipeline.path), field=f"publish.{ref}"
        )
    return str(digest)


def _publish_one(session: Session, state: StageState, ref: str, dest: Path) -> None:
    """Export one ``publish:`` entry to ``dest``; errors name the entry."""
    stage, _, output = ref.partition(".")
    assert state.key is not None
    try:
        export_output(session.store.open(state.key), output, dest, field=f"publish.{ref}")
    except CorruptArtifact as exc:
        raise exc.located(stage=stage) from None
    except UserError as exc:
        raise UserError(
            f"{display_path(dest)}: {exc.message}", file=str(session.pipeline.path), field=f"publish.{ref}"
        ) from None
