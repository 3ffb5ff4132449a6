"""Mood Swings pipeline stages, one package per part of the paper's Fig. 1.

- ``tracking``: video to landmarks, mesh, head pose, face crops and audio (Sec 3.1);
- ``face``: appearance model, bilinear model, expression analysis and edit (Sec 3, Eq 1-7);
- ``retarget``: character, keyshapes, keymorphs, expression blend (Sec 4, Eq 8-9);
- ``head``: motion database, pitch segmentation, trellis search, motion blending (Sec 5, Eq 10-15);
- ``export``: the animation as GLB, Live Link Face CSV, BVH and preview video;
- ``formats`` and ``geometry``: file formats and shared maths used by the above.
"""
