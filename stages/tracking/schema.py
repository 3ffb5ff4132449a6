"""Output schema shared by every tracking implementation (FaceMesh, OpticalFlow, TrackFile).

All sequences (one per labelled input video) are concatenated along the frame axis; ``sequence`` gives each
frame's index into ``meta["labels"]``. Metadata (strict JSON) holds per sequence: ``labels``, ``sources`` (file
names), ``fps``, ``frame_size`` [w, h], ``audio_rate``, ``audio_offset`` (seconds of the first audio sample
relative to the first video frame), plus ``landmark_scheme`` ("ibug68"), ``focal_length`` and crop settings.
"""

from msflow import Output

TRACKING_OUTPUTS = {
    "landmarks": Output.array(
        "f", shape=("frames", 68, 2), dtype="float32", doc="68 iBUG/OpenFace points in image pixels (x right, y down)"
    ),
    "mesh": Output.array(
        "f",
        shape=("frames", 468, 3),
        dtype="float32",
        optional=True,
        doc="FaceMesh 468 points: x, y image pixels, z relative depth in pixels",
    ),
    "confidence": Output.array("f", shape=("frames",), dtype="float32", doc="face presence / tracking score 0..1"),
    "valid": Output.array("b", shape=("frames",), doc="False where no face was found and landmarks were interpolated"),
    "time": Output.array("f", shape=("frames",), dtype="float64", doc="seconds since the sequence's first frame"),
    "sequence": Output.array("i", shape=("frames",), dtype="int32", doc="index into meta['labels']"),
    "rotation": Output.array(
        "f",
        shape=("frames", 4),
        dtype="float64",
        doc="head rotation, unit quaternion (w, x, y, z) in the stages.geometry.rotations convention",
    ),
    "translation": Output.array(
        "f",
        shape=("frames", 3),
        dtype="float64",
        doc="head position in camera space, glTF axes, units in meta['translation_units']",
    ),
    "crops": Output.array(
        "u",
        shape=("frames", None, None),
        dtype="uint8",
        doc="grayscale face crops: similarity-normalised (eyes level, fixed inter-ocular distance)",
    ),
    "crop_landmarks": Output.array("f", shape=("frames", 68, 2), dtype="float32", doc="landmarks in crop pixels"),
    "crop_transforms": Output.array(
        "f", shape=("frames", 2, 3), dtype="float64", doc="2x3 similarity mapping image pixels to crop pixels"
    ),
    "pose_rms": Output.array(
        "f",
        shape=("frames",),
        dtype="float32",
        optional=True,
        doc="head-pose fit: RMS reprojection error of the 3D face's landmarks (pixels)",
    ),
    "audio": Output.array(
        "f",
        shape=("samples",),
        dtype="float32",
        optional=True,
        doc="mono audio of all sequences concatenated, meta['audio_rate'] Hz",
    ),
    "audio_bounds": Output.array(
        "i", shape=(None, 2), dtype="int64", optional=True, doc="per sequence [start, stop) sample indices into 'audio'"
    ),
}
