"""Export of the final animation: GLB with morph and head animation, Live Link Face CSV, BVH, preview video."""
