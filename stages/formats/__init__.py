"""File formats read and written by the stages: glTF (GLB), BVH, audio decoding; no stage classes here."""
