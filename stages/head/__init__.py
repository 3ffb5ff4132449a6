"""Head motion from the voice (paper Sec 5).

- ``database``: the motion database: (audio, head pose) pairs from tracked takes, BVH or CSV;
- ``pitch``: pitch tracking and segmentation at voiced onsets, phrase features (Sec 5.1-5.2);
- ``trellis``: phrase and segment matching and the Viterbi search over candidates (Eq 10-15);
- ``motion_blend``: resampling, chaining, drift correction and smoothing of the chosen segments (Sec 5.4).
"""
