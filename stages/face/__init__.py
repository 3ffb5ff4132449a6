"""Face analysis (paper Sec 3): the appearance model, content alignment, the bilinear model and the expression edit.

- ``aam``: Procrustes shape PCA (Eq 1), shape-normalised texture PCA (Eq 2), combined vector y (Eq 3);
- ``warp``: piecewise-affine warps onto the mean shape (the texture half of Eq 2);
- ``alignment``: which take plays which expression (fields), and DTW content alignment of the takes before the fit;
- ``bilinear``: the symmetric bilinear model y = e' W_k c (Eq 4, Tenenbaum & Freeman);
- ``analysis``: per-frame style and content of a new take (Eq 5-6) and its classification;
- ``edit``: the take's resynthesis in other expressions (Eq 7) and the edited face images.
"""
