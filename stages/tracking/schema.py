"""Output schema shared by every tracking implementation (FaceMesh, OpticalFlow, TrackFile).

All sequences (one per labelled input video) are concatenated along the frame axis; ``sequence`` gives each
frame's index into ``meta["labels"]``. Metadata (strict JSON) holds per sequence: ``labels``, ``sources`` (file
names), ``fps``, ``frame_size`` [w, h], ``audio_rate``, ``audio_offset`` (seconds of the first audio sample
relative to the first video frame), ``has_audio``, ``audio_sources``, ``gaps`` (long gaps held, [start, stop)
frames), plus ``fields`` ({label: {field: value}}), ``landmark_scheme`` ("ibug68"), ``focal_length`` and crop
settings. Eye outputs (``eye_aperture``, ``gaze``, ``iris``) come with FaceMesh's eye pass (``eyes``: Face
Landmarker v2 by default, or the iris model); their conventions are in stages/tracking/eyes.py.
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
    "eye_aperture": Output.array(
        "f",
        shape=("frames", 2),
        dtype="float32",
        optional=True,
        doc="eyelid gap over eye width (eye aspect ratio): [:, 0] the performer's left eye (ARKit _L), [:, 1] right; "
        "about 0.25-0.35 open, below 0.1 closed (Face Landmarker v2; the iris model's lids stop at about 0.13)",
    ),
    "gaze": Output.array(
        "f",
        shape=("frames", 2, 2),
        dtype="float32",
        optional=True,
        doc="eyeball rotation relative to the head, degrees: [eye (0 left, 1 right)][yaw, pitch], yaw > 0 towards "
        "the performer's left, pitch > 0 up (FaceMesh with an eye pass)",
    ),
    "iris": Output.array(
        "f",
        shape=("frames", 10, 3),
        dtype="float32",
        optional=True,
        doc="the model's 10 iris points as it orders them (0-4: centre and rim of the performer's right eye, 5-9: "
        "left eye), image pixels like 'mesh' (FaceMesh with an eye pass)",
    ),
    "confidence": Output.array("f", shape=("frames",), dtype="float32", doc="face presence / tracking score 0..1"),
    "valid": Output.array(
        "b",
        shape=("frames",),
        doc="False where no face was found: values interpolated across a short gap, or held through a long one",
    ),
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
