"""Writing one artifact output to a file (``msflow export``, ``publish:``): .npy, .npz, .csv, .json, or the raw
bytes of a file output (GLB, MP4, CSV ... produced by a stage)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from msflow.errors import UserError

ARRAY_SUFFIXES = (".npy", ".npz", ".csv", ".json")


def export_output(view, output: str, dest: Path) -> None:
    import numpy as np

    if output not in view:
        raise UserError(f"no output '{output}'; outputs: {', '.join(view.names)}", field="STAGE.output")
    entry = view.manifest.get("outputs", {}).get(output, {})
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.tmp")
    suffix = dest.suffix.lower()
    arr = view[output]
    if entry.get("file_suffix"):
        tmp.write_bytes(arr.tobytes())
    elif suffix == ".npy":
        with open(tmp, "wb") as fh:
            np.save(fh, arr, allow_pickle=False)
    elif suffix == ".npz":
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **{output: arr})
    elif suffix == ".csv":
        tmp.write_text(array_to_csv(arr, output), encoding="utf-8")
    elif suffix == ".json":
        data = np.where(np.isfinite(arr), arr, np.nan).tolist() if arr.dtype.kind == "f" else arr.tolist()
        tmp.write_text(
            json.dumps({"name": output, "shape": list(arr.shape), "dtype": str(arr.dtype), "data": _nan_to_none(data)}),
            encoding="utf-8",
        )
    else:
        raise UserError(
            f"unsupported export format '{suffix or dest.name}'; use one of {', '.join(ARRAY_SUFFIXES)}",
            file=str(dest),
            field="FILE",
        )
    os.replace(tmp, dest)


def array_to_csv(arr, name: str) -> str:
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


def _nan_to_none(value):
    if isinstance(value, list):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, float) and value != value:
        return None
    return value


def publish_outputs(session, states) -> list[str]:
    """Materialise the pipeline's ``publish:`` entries; skip files already holding the same output content."""
    from msflow.hashing import stat_signature

    published = session.memo.setdefault("published", {})
    written = []
    for ref, dest in session.pipeline.publish.items():
        stage, _, output = ref.partition(".")
        state = states.get(stage)
        if state is None or state.state not in ("cached", "ran"):
            continue
        digest = state.manifest["outputs"].get(output, {}).get("hash")
        if digest is None:
            raise UserError(
                f"stage '{stage}' has no output '{output}'", file=str(session.pipeline.path), field=f"publish.{ref}"
            )
        previous = published.get(dest)
        if previous and previous[0] == digest and os.path.exists(dest) and previous[1] == stat_signature(Path(dest)):
            continue
        export_output(session.store.open(state.key), output, Path(dest))
        published[dest] = [digest, stat_signature(Path(dest))]
        written.append(dest)
    return written
