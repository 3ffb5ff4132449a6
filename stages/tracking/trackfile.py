"""Reading and writing landmark tracks: OpenFace 2.0 CSV, plain CSV, .npz and iBUG .pts (one file per frame).

- OpenFace 2.0 (FeatureExtraction / FaceLandmarkVid) CSV: header ``frame, face_id, timestamp, confidence,
  success, ..., pose_Tx, pose_Ty, pose_Tz, pose_Rx, pose_Ry, pose_Rz, ..., x_0 .. x_67, y_0 .. y_67, ...``,
  separators ", ", frame numbers from 1. Rows with success = 0 are frames where OpenFace lost the face.
- Plain CSV: ``frame,x_0..x_67,y_0..y_67`` (frame numbers from 0; optional ``timestamp``, ``confidence``,
  ``success`` columns).
- .npz (read with allow_pickle=False): ``landmarks`` (frames, 68, 2); optional ``valid``, ``confidence``,
  ``time``, ``frame``, ``fps``, ``frame_size`` [w, h].
- iBUG .pts: ``version: 1`` / ``n_points: 68`` / ``{`` x y lines ``}``; a sequence is a directory of .pts
  files in natural name order, or a single file (one frame).
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msflow import UserError

N_POINTS = 68
OPENFACE_POSE = ("pose_Tx", "pose_Ty", "pose_Tz", "pose_Rx", "pose_Ry", "pose_Rz")


@dataclass
class FileTrack:
    """Landmarks as a file holds them. ``frame`` is the 0-based video frame of each row."""

    landmarks: np.ndarray  # (rows, 68, 2) float64, NaN where missing
    valid: np.ndarray  # (rows,) bool
    confidence: np.ndarray  # (rows,) float64 in 0..1
    frame: np.ndarray  # (rows,) int64, strictly increasing
    time: np.ndarray | None = None  # (rows,) seconds, as stored
    fps: float | None = None
    frame_size: tuple[int, int] | None = None
    openface_pose: np.ndarray | None = None  # (rows, 6) pose_Tx..pose_Rz as stored
    format: str = ""
    extra: dict = field(default_factory=dict)


def detect_format(path: Path) -> str:
    if path.is_dir():
        return "pts"
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return "npz"
    if suffix == ".pts":
        return "pts"
    if suffix in (".csv", ".txt"):
        header = _read_header(path)
        return "openface" if {"success", "face_id"} & set(header) else "csv"
    raise UserError(
        f"cannot tell the track format from the suffix '{suffix}' (use .csv, .npz, .pts or a "
        f"directory of .pts files, or set params.format)",
        file=str(path),
    )


def read_track(
    path: str | Path, fmt: str = "auto", *, frame_base: int | None = None, face_id: int = 0, field: str | None = None
) -> FileTrack:
    """Read one track file in the given (or detected) format; UserError naming the file on bad content."""
    path = Path(path)
    if not path.exists():
        raise UserError("track file not found", file=str(path), field=field)
    fmt = detect_format(path) if fmt == "auto" else fmt
    try:
        if fmt in ("openface", "csv"):
            track = read_csv_track(path, openface=fmt == "openface", frame_base=frame_base, face_id=face_id)
        elif fmt == "npz":
            track = read_npz_track(path, frame_base=frame_base)
        elif fmt == "pts":
            track = read_pts_sequence(path)
        else:
            raise UserError(f"unknown track format '{fmt}'")
    except UserError as err:
        raise err.located(file=str(path), field=field) from None
    track.format = fmt
    _check_frames(track.frame, path, field)
    return track


def _check_frames(frame: np.ndarray, path: Path, field: str | None) -> None:
    if len(frame) == 0:
        raise UserError("track holds no frames", file=str(path), field=field)
    if (frame < 0).any():
        raise UserError(
            f"negative frame number {int(frame.min())} (check params.frame_base)", file=str(path), field=field
        )
    if (np.diff(frame) <= 0).any():
        bad = int(np.flatnonzero(np.diff(frame) <= 0)[0])
        raise UserError(
            f"frame numbers must increase: row {bad + 2} has frame {int(frame[bad + 1])} after {int(frame[bad])}",
            file=str(path),
            field=field,
        )


# ---------------------------------------------------------------- CSV (OpenFace 2.0 and plain)


def _read_header(path: Path) -> list[str]:
    with open(path, encoding="utf-8", errors="replace") as fh:
        return [c.strip() for c in fh.readline().split(",")]


def _landmark_columns(header: list[str]) -> tuple[list[int], list[int]]:
    """Column indices of x_0..x_{n-1} and y_0..y_{n-1}; UserError when the count is not 68 or one is missing."""
    xs = {int(m.group(1)): i for i, c in enumerate(header) if (m := re.fullmatch(r"x_(\d+)", c))}
    ys = {int(m.group(1)): i for i, c in enumerate(header) if (m := re.fullmatch(r"y_(\d+)", c))}
    if not xs and not ys:
        raise UserError("no landmark columns x_0..x_67, y_0..y_67 in the header")
    count = max(list(xs) + list(ys)) + 1
    if count != N_POINTS:
        raise UserError(f"track has {count} landmarks (x_0..x_{count - 1}); 68 (iBUG scheme) are needed")
    missing = [f"x_{i}" for i in range(N_POINTS) if i not in xs] + [f"y_{i}" for i in range(N_POINTS) if i not in ys]
    if missing:
        raise UserError(f"missing landmark columns: {', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}")
    return [xs[i] for i in range(N_POINTS)], [ys[i] for i in range(N_POINTS)]


def read_csv_track(path: Path, *, openface: bool, frame_base: int | None = None, face_id: int = 0) -> FileTrack:
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines:
        raise UserError("empty CSV file")
    header = [c.strip() for c in lines[0].split(",")]
    col = {name: i for i, name in enumerate(header)}
    required = ["frame", "timestamp", "confidence", "success"] if openface else []
    missing = [c for c in required if c not in col]
    if missing:
        raise UserError(
            f"not an OpenFace 2.0 CSV: missing columns {', '.join(missing)} (found "
            f"{', '.join(header[:6])}{' ...' if len(header) > 6 else ''})"
        )
    xcols, ycols = _landmark_columns(header)
    if len(lines) < 2:
        raise UserError("CSV has a header but no rows")
    try:
        data = np.loadtxt(io.StringIO("\n".join(lines[1:])), delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise UserError(f"CSV rows are not all numbers with {len(header)} columns ({exc})") from None
    if data.shape[1] != len(header):
        raise UserError(f"CSV rows have {data.shape[1]} values but the header names {len(header)} columns")
    if "face_id" in col:
        ids = data[:, col["face_id"]]
        if not (ids == face_id).any():
            raise UserError(f"no rows for face_id {face_id} (found {sorted(set(ids.astype(int).tolist()))[:10]})")
        data = data[ids == face_id]
    landmarks = np.stack([data[:, xcols], data[:, ycols]], axis=-1)
    base = frame_base if frame_base is not None else (1 if openface else 0)
    frame = (data[:, col["frame"]].astype(np.int64) - base) if "frame" in col else np.arange(len(data))
    valid = data[:, col["success"]] > 0.5 if "success" in col else np.ones(len(data), dtype=bool)
    valid &= np.isfinite(landmarks).all(axis=(1, 2))
    confidence = np.clip(data[:, col["confidence"]], 0, 1) if "confidence" in col else valid.astype(np.float64)
    time = data[:, col["timestamp"]] if "timestamp" in col else None
    pose = data[:, [col[c] for c in OPENFACE_POSE]] if all(c in col for c in OPENFACE_POSE) else None
    landmarks = np.where(valid[:, None, None], landmarks, np.nan)
    return FileTrack(landmarks, valid, np.where(valid, confidence, 0.0), frame, time, None, None, pose)


def write_openface_csv(
    landmarks: np.ndarray,
    *,
    time: np.ndarray | None = None,
    fps: float = 30.0,
    confidence: np.ndarray | None = None,
    success: np.ndarray | None = None,
    pose: np.ndarray | None = None,
    face_id: int = 0,
) -> str:
    """OpenFace 2.0-style CSV text (", " separators, frames from 1); rows with success 0 get zero landmarks,
    as OpenFace writes them. ``pose``: (frames, 6) pose_Tx..pose_Rz in OpenFace's convention."""
    lm = np.asarray(landmarks, dtype=np.float64)
    n = len(lm)
    time = np.arange(n) / fps if time is None else np.asarray(time)
    success = np.ones(n, dtype=bool) if success is None else np.asarray(success, dtype=bool)
    confidence = np.where(success, 0.98, 0.0) if confidence is None else np.asarray(confidence)
    header = ["frame", "face_id", "timestamp", "confidence", "success"]
    cols = [np.arange(1, n + 1), np.full(n, face_id), time, confidence, success.astype(int)]
    if pose is not None:
        header += list(OPENFACE_POSE)
        cols += list(np.asarray(pose, dtype=np.float64).T)
    header += [f"x_{i}" for i in range(N_POINTS)] + [f"y_{i}" for i in range(N_POINTS)]
    lm = np.where(success[:, None, None], np.nan_to_num(lm), 0.0)
    cols += list(lm[:, :, 0].T) + list(lm[:, :, 1].T)
    table = np.column_stack(cols)
    out = io.StringIO()
    out.write(", ".join(header) + "\n")
    fmt = ["%d", "%d", "%.3f", "%.2f", "%d"] + ["%.6f"] * (len(header) - 5)
    np.savetxt(out, table, fmt=fmt, delimiter=", ")
    return out.getvalue()


def write_plain_csv(landmarks: np.ndarray, frames: np.ndarray | None = None) -> str:
    """``frame,x_0..x_67,y_0..y_67`` CSV text, frames from 0."""
    lm = np.asarray(landmarks, dtype=np.float64)
    frames = np.arange(len(lm)) if frames is None else np.asarray(frames)
    header = ["frame"] + [f"x_{i}" for i in range(N_POINTS)] + [f"y_{i}" for i in range(N_POINTS)]
    out = io.StringIO()
    out.write(",".join(header) + "\n")
    np.savetxt(out, np.column_stack([frames, lm[:, :, 0], lm[:, :, 1]]), fmt=["%d"] + ["%.6f"] * 136, delimiter=",")
    return out.getvalue()


# ---------------------------------------------------------------- .npz


def read_npz_track(path: Path, *, frame_base: int | None = None) -> FileTrack:
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (ValueError, OSError) as exc:
        raise UserError(f"cannot read .npz (object arrays are not accepted) ({exc})") from None
    if "landmarks" not in data:
        raise UserError(f"no 'landmarks' array in the .npz (found {', '.join(sorted(data)) or 'none'})")
    lm = np.asarray(data["landmarks"], dtype=np.float64)
    if lm.ndim == 2 and lm.shape[1] == 2 * N_POINTS:
        lm = lm.reshape(len(lm), N_POINTS, 2)
    if lm.ndim != 3 or lm.shape[2] != 2:
        raise UserError(f"'landmarks' must be (frames, 68, 2), got {lm.shape}")
    if lm.shape[1] != N_POINTS:
        raise UserError(f"track has {lm.shape[1]} landmarks per frame; 68 (iBUG scheme) are needed")
    n = len(lm)
    valid = np.asarray(data.get("valid", data.get("success", np.ones(n))), dtype=bool).reshape(-1)
    if len(valid) != n:
        raise UserError(f"'valid' has {len(valid)} entries for {n} frames")
    valid &= np.isfinite(lm).all(axis=(1, 2))
    conf = np.asarray(data.get("confidence", valid.astype(np.float64)), dtype=np.float64).reshape(-1)
    frame = (
        np.asarray(data["frame"], dtype=np.int64).reshape(-1) - (frame_base or 0) if "frame" in data else np.arange(n)
    )
    time = np.asarray(data["time"], dtype=np.float64).reshape(-1) if "time" in data else None
    fps = float(data["fps"]) if "fps" in data else None
    size = tuple(int(v) for v in np.asarray(data["frame_size"]).reshape(-1)[:2]) if "frame_size" in data else None
    for name, arr in (("confidence", conf), ("frame", frame), ("time", time)):
        if arr is not None and len(arr) != n:
            raise UserError(f"'{name}' has {len(arr)} entries for {n} frames")
    lm = np.where(valid[:, None, None], lm, np.nan)
    return FileTrack(lm, valid, np.where(valid, np.clip(conf, 0, 1), 0.0), frame, time, fps, size)


def write_npz(landmarks: np.ndarray, **arrays) -> bytes:
    """.npz bytes with ``landmarks`` and any extra plain arrays (valid, confidence, time, frame, fps, ...)."""
    out = io.BytesIO()
    np.savez_compressed(out, landmarks=np.asarray(landmarks), **{k: np.asarray(v) for k, v in arrays.items()})
    return out.getvalue()


# ---------------------------------------------------------------- iBUG .pts


def parse_pts(text: str) -> np.ndarray:
    """(n, 2) points of one iBUG .pts file's text; UserError when malformed or not 68 points."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    n_declared = None
    for ln in lines:
        if ln.lower().startswith("n_points"):
            try:
                n_declared = int(ln.split(":", 1)[1])
            except (IndexError, ValueError):
                raise UserError(f"bad n_points line '{ln}'") from None
    try:
        start, stop = lines.index("{"), lines.index("}")
    except ValueError:
        raise UserError("not an iBUG .pts file: no '{' ... '}' block") from None
    try:
        pts = np.array([[float(v) for v in ln.split()[:2]] for ln in lines[start + 1 : stop]], dtype=np.float64)
    except ValueError:
        raise UserError("point lines must hold two numbers") from None
    if n_declared is not None and n_declared != len(pts):
        raise UserError(f"n_points says {n_declared} but the file lists {len(pts)} points")
    if len(pts) != N_POINTS:
        raise UserError(f"has {len(pts)} points; 68 (iBUG scheme) are needed")
    return pts


def format_pts(points: np.ndarray) -> str:
    pts = np.asarray(points, dtype=np.float64)
    body = "\n".join(f"{x:.3f} {y:.3f}" for x, y in pts)
    return f"version: 1\nn_points: {len(pts)}\n{{\n{body}\n}}\n"


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def read_pts_sequence(path: Path) -> FileTrack:
    files = sorted(path.glob("*.pts"), key=_natural_key) if path.is_dir() else [path]
    if not files:
        raise UserError("directory holds no .pts files")
    shapes = []
    for f in files:
        try:
            shapes.append(parse_pts(f.read_text(encoding="utf-8", errors="replace")))
        except UserError as err:
            raise err.located(file=str(f)) from None
    lm = np.stack(shapes)
    n = len(lm)
    return FileTrack(lm, np.ones(n, dtype=bool), np.ones(n), np.arange(n), extra={"files": [f.name for f in files]})
