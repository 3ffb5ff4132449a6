"""FaceMesh over a take as a stream: decode -> landmarks -> gap filling -> blocks of frames -> outputs.

Memory stays bounded whatever the take's length: a frame's picture is dropped as soon as its landmarks and face
crop are made; only the frames of an open gap of at most ``max_gap_frames`` keep their luma plane (their crops
need the interpolated landmarks, known when the face comes back); everything per frame is gathered in blocks of
``BLOCK_FRAMES`` and handed to the outputs block by block (landmarks -> 68 points, crops, head pose, eyes), so the
big outputs (crops, mesh) can go straight to the store. Results do not depend on the block size: every per-frame
quantity is computed frame by frame or vectorised over frames, and head pose carries its solver state across
blocks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msflow import UserError
from stages.tracking.crops import apply_transforms, similarity_transform
from stages.tracking.gaps import FILLED, HELD, TRACKED, long_gap_error
from stages.tracking.landmarks68 import mesh_to_ibug68

#: frames per block handed to the outputs
BLOCK_FRAMES = 256


@dataclass
class FrameRecord:
    """One decoded frame after the landmark model: its points (None: no face), and its crop once made."""

    time: float
    points: np.ndarray | None
    score: float
    crop: np.ndarray | None = None
    transform: np.ndarray | None = None
    image: object | None = None  # the luma plane, kept only while the frame waits in a short gap


@dataclass
class FilledFrame:
    """A frame ready for the outputs: its (possibly filled) points and how they were made (gaps.TRACKED, FILLED,
    HELD); ``crop``/``transform`` are set when they come from a tracked frame, else made from ``record.image``."""

    record: FrameRecord
    points: np.ndarray
    kind: int
    crop: np.ndarray | None
    transform: np.ndarray | None


class GapFiller:
    """``gaps.gap_plan`` on a stream: frames in, in order; frames out as soon as their values are known.

    A frame without a face waits until the face comes back (then a gap of at most ``max_gap`` frames is
    interpolated) or until the gap grows longer than ``max_gap`` (then it and the rest of the gap hold the last
    tracked frame, crops included, and go out at once). A long gap at the start waits for the first face and
    holds it. Frames of a gap keep their picture only while the gap is short.
    """

    def __init__(self, max_gap: int):
        self.max_gap = max_gap
        self.last: FrameRecord | None = None
        self.pending: list[FrameRecord] = []
        self.gap = 0

    def push(self, rec: FrameRecord) -> list[FilledFrame]:
        if rec.points is not None:
            out = self._close_gap(rec) if self.gap else []
            self.last = rec
            out.append(FilledFrame(rec, rec.points, TRACKED, rec.crop, rec.transform))
            return out
        self.gap += 1
        self.pending.append(rec)
        if self.gap <= self.max_gap:
            return []
        for waiting in self.pending:  # a long gap: no crop will be made from these pictures
            waiting.image = None
        if self.last is None:
            return []
        return self._hold(self.last, HELD)

    def finish(self) -> list[FilledFrame]:
        """The frames of a gap still open at the end of the take (holding the last tracked frame)."""
        if not self.pending:
            return []
        if self.last is None:
            return []  # no face at all: the caller reports it
        return self._hold(self.last, FILLED if self.gap <= self.max_gap else HELD)

    def _hold(self, source: FrameRecord, kind: int) -> list[FilledFrame]:
        crop, transform = (source.crop, source.transform) if kind == HELD else (None, None)
        out = [FilledFrame(r, source.points, kind, crop, transform) for r in self.pending]
        self.pending = []
        return out

    def _close_gap(self, nxt: FrameRecord) -> list[FilledFrame]:
        length, prev = self.gap, self.last
        self.gap = 0
        if length > self.max_gap or prev is None:
            return self._hold(nxt, HELD if length > self.max_gap else FILLED)
        out = []
        for k, rec in enumerate(self.pending, start=1):
            w = k / (length + 1)  # k frames after the last tracked frame, as gaps.gap_plan
            out.append(FilledFrame(rec, (1 - w) * prev.points + w * nxt.points, FILLED, None, None))
        self.pending = []
        return out


@dataclass
class CropSettings:
    size: int
    eye_distance: float
    eye_height: float

    def transform(self, landmarks: np.ndarray) -> np.ndarray:
        return similarity_transform(landmarks, self.size, self.eye_distance, self.eye_height)


@dataclass
class TakeSummary:
    """What stays in memory of a take once its frames went to the outputs: the small per-frame arrays."""

    time: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray
    landmarks: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    pose_rms: np.ndarray
    kinds: np.ndarray
    meta: dict = field(default_factory=dict)


#: frames a take's focal length is estimated from (``BlockWriter`` ``focal_frames``): 20 s at 30 fps, every one of
#: ``shapes3d.estimate_focal``'s frames; they wait, with their crops, until it is known (about 15 MB)
FOCAL_FRAMES = 600


class BlockWriter:
    """Gathers filled frames into blocks and hands each block's outputs to ``emit(arrays)``.

    Per block: the 68 points from the mesh, crops for frames filled in a short gap, crop landmarks, head pose
    (``pose_solver``, stateful across blocks), and the eyes from the 478-point layout starting at ``eye_offset``
    in each frame's points (None: no eye outputs). Keeps the small per-frame arrays for the take's summary.
    With ``focal_frames``, the first blocks wait for that many frames (or the take's end) and the pose solver's
    focal length is first set to the one their mesh says (``calibrate_focal``), so the result does not depend
    on the block size.
    """

    def __init__(
        self,
        n_points: int,
        crop: CropSettings,
        pose_solver,
        emit,
        keep_mesh: bool,
        eye_offset: int | None = None,
        block: int = 0,
        eye_rest: tuple[float, float] | None = None,
        focal_frames: int = 0,
    ):
        self.n_points, self.crop, self.pose, self.emit = n_points, crop, pose_solver, emit
        self.focal_frames = focal_frames
        self.keep_mesh, self.eye_offset, self.block = keep_mesh, eye_offset, block or BLOCK_FRAMES
        self.eye_rest = eye_rest  # the eye pass's straight-ahead iris position (eyes.REST_OFFSETS); None: v2's
        self.frames: list[FilledFrame] = []
        self.summary: dict[str, list[np.ndarray]] = {}

    def add(self, frames: list[FilledFrame]) -> None:
        self.frames.extend(frames)
        if self.focal_frames and len(self.frames) < self.focal_frames:
            return
        self._calibrate()
        while len(self.frames) >= self.block:
            self._flush(self.frames[: self.block])
            self.frames = self.frames[self.block :]

    def finish(self) -> TakeSummary:
        self._calibrate()
        if self.frames:
            self._flush(self.frames)
            self.frames = []
        cat = {k: np.concatenate(v) for k, v in self.summary.items()}
        return TakeSummary(**cat)

    def _calibrate(self) -> None:
        """Once, before the first block: the pose solver's focal length from the waiting frames' mesh."""
        if not self.focal_frames or not self.frames:
            return
        mesh = np.stack([f.points for f in self.frames[: self.focal_frames]]).reshape(-1, self.n_points, 3)
        self.pose.camera = calibrate_focal(mesh[:, :468], self.pose.camera)
        self.focal_frames = 0

    def _flush(self, frames: list[FilledFrame]) -> None:
        arrays = block_arrays(frames, self.n_points, self.crop)
        rotation, translation, rms = self.pose.solve(arrays.pop("landmarks64"))
        arrays.update(rotation=rotation, translation=translation, pose_rms=rms.astype(np.float32))
        if self.eye_offset is not None:
            from stages.tracking.eyes import REST_OFFSET, eye_aperture, gaze_angles

            eye_points = arrays["points"][:, self.eye_offset : self.eye_offset + 478]
            arrays["eye_aperture"] = eye_aperture(eye_points)
            arrays["gaze"] = gaze_angles(eye_points, rest=self.eye_rest or REST_OFFSET)
            arrays["iris"] = eye_points[:, 468:478].astype(np.float32)
        points = arrays.pop("points")
        if self.keep_mesh:
            arrays["mesh"] = points[:, :468].astype(np.float32)
        for key in ("time", "valid", "confidence", "landmarks", "rotation", "translation", "pose_rms", "kinds"):
            self.summary.setdefault(key, []).append(arrays[key])
        self.emit({k: v for k, v in arrays.items() if k != "kinds"})


#: the longest lens ``calibrate_focal`` tries, as a multiple of ``camera``'s (the frame width): beyond it a head is
#: seen almost without perspective, so the rigid points hardly tell lenses apart (a still head's estimate then
#: wanders, up to "none at all"), and the pose hardly depends on which
LONGEST_LENS = 4.0


def calibrate_focal(mesh: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """``camera`` with the focal length that leaves the FaceMesh frames ``mesh`` (frames, 468, 3) most rigid
    (``shapes3d.estimate_focal`` over its lenses up to ``LONGEST_LENS`` times ``camera``'s; a still head keeps
    ``camera``'s)."""
    from stages.retarget.shapes3d import FOCAL_MULTIPLES, estimate_focal, with_focal

    lenses = [m for m in FOCAL_MULTIPLES if m <= LONGEST_LENS]
    return with_focal(camera, estimate_focal(mesh, camera, lenses)[0])


def block_arrays(frames: list[FilledFrame], n_points: int, crop: CropSettings) -> dict:
    """The per-frame arrays of one block: points, 68 landmarks, crops and their transforms, time, scores."""
    n = len(frames)
    points = np.stack([f.points for f in frames]).reshape(n, n_points, 3)
    landmarks = mesh_to_ibug68(points[:, :468, :2])
    crops = np.empty((n, crop.size, crop.size), dtype=np.uint8)
    transforms = np.empty((n, 2, 3))
    for i, f in enumerate(frames):
        if f.crop is None:  # filled in a short gap: cropped from its own picture at the filled landmarks
            transforms[i] = crop.transform(landmarks[i])
            crops[i] = f.record.image.warp_gray(transforms[i], crop.size)
            f.record.image = None
        else:
            crops[i], transforms[i] = f.crop, f.transform
    kinds = np.array([f.kind for f in frames], dtype=np.int8)
    return {
        "points": points,
        "landmarks64": landmarks,
        "landmarks": landmarks.astype(np.float32),
        "crops": crops,
        "crop_transforms": transforms,
        # from the stored (float32) landmarks, so crop_landmarks map exactly what the artifact holds
        "crop_landmarks": apply_transforms(landmarks.astype(np.float32).astype(np.float64), transforms).astype(
            np.float32
        ),
        "time": np.array([f.record.time for f in frames], dtype=np.float64),
        "valid": kinds == TRACKED,
        "confidence": np.array([f.record.score if f.kind == TRACKED else 0.0 for f in frames], dtype=np.float32),
        "kinds": kinds,
    }


def track_frame(tracker, t: float, image, crop: CropSettings, keep_image: bool) -> FrameRecord:
    """Landmarks of one frame; a tracked frame is cropped at once (its picture is then no longer needed)."""
    points, score = tracker.step(image)
    rec = FrameRecord(t, points, score)
    if points is not None:
        landmarks = mesh_to_ibug68(points[:468, :2])
        rec.transform = crop.transform(landmarks)
        rec.crop = image.warp_gray(rec.transform, crop.size)
    elif keep_image:
        rec.image = luma_copy(image)
    return rec


def luma_copy(image):
    """What a frame waiting in a gap keeps: the whole frame in gray (enough for ``warp_gray``)."""
    return image.gray_image()


def stream_take(frames, tracker, writer: BlockWriter, crop: CropSettings, max_gap: int, path: Path, field: str):
    """Track every (time, image) of ``frames`` into ``writer``; UserError when no frame has a face."""
    filler = GapFiller(max_gap)
    count = 0
    for t, image in frames:
        rec = track_frame(tracker, t, image, crop, keep_image=filler.gap < max_gap)
        writer.add(filler.push(rec))
        count += 1
    if filler.last is None:
        raise UserError(f"no face found in any of its {count} frames", file=str(path), field=field)
    writer.add(filler.finish())


def check_gaps(summary: TakeSummary, max_gap: int, long_gaps: str, path: Path, field: str) -> list:
    """UserError when (``long_gaps`` 'error') a gap is longer than ``max_gap``; else the long gaps as
    [start, stop) frame ranges (held and marked in ``valid``)."""
    from stages.tracking.gaps import find_gaps

    long = [(a, b) for a, b in find_gaps(summary.valid) if b - a > max_gap]
    if long and long_gaps == "error":
        raise long_gap_error(summary.valid, max_gap, summary.time, file=str(path), field=field)
    return long


__all__ = [
    "BLOCK_FRAMES",
    "FOCAL_FRAMES",
    "GapFiller",
    "BlockWriter",
    "CropSettings",
    "TakeSummary",
    "stream_take",
    "check_gaps",
]
