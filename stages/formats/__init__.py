"""File formats read and written by the stages: glTF (GLB), BVH, audio decoding, MP4 writing; no stage classes here."""
