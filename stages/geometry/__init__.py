"""Geometry shared by the stages: rotations and their conventions, the z-buffer rasteriser, batched NNLS."""
