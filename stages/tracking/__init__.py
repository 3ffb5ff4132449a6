"""Tracking ingest (paper Fig. 1 "tracking"): labelled videos or track files in, per-frame 68 iBUG landmarks,
head pose, face crops and audio out, in one schema (schema.TRACKING_OUTPUTS) for every implementation:

- ``FaceMesh``: MediaPipe BlazeFace + 468-point face mesh through OpenCV DNN (default);
- ``OpticalFlow``: pyramidal Lucas-Kanade with a forward-backward check and a shape-model constraint;
- ``TrackFile``: OpenFace 2.0 CSV, plain CSV, .npz or iBUG .pts tracks, no video analysis.
"""

from stages.tracking.schema import TRACKING_OUTPUTS
from stages.tracking.stages import FaceMesh, OpticalFlow, TrackFile

__all__ = ["FaceMesh", "OpticalFlow", "TrackFile", "TRACKING_OUTPUTS"]
