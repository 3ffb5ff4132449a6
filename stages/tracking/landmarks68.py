"""The 68-point iBUG/OpenFace scheme from MediaPipe's 468-point face mesh.

Each iBUG point is one mesh vertex or the mean of two neighbouring vertices on the same contour. The table was
set up by following each iBUG contour along the mesh vertices that lie on it and placing the in-between points
at the iBUG rule of equal spacing along the contour (arc length measured on the six CREMA-D clips; see
``contour_fractions`` and tests/test_tracking_landmarks68.py, which checks the spacing and the left/right
symmetry of the table). "Right"/"left" are the subject's: iBUG point 0 is on the image's left.

| iBUG  | part                    | mesh vertices (mean when two)                                                  |
|-------|-------------------------|--------------------------------------------------------------------------------|
| 0-16  | jaw, subject's right ear to left ear, 8 = chin | 127 · 234 · 93+132 · 132+58 · 58+172 · 136 · 150+149 · 176+148 · 152 · 377+400 · 378+379 · 365 · 397+288 · 288+361 · 361+323 · 454 · 356 |
| 17-21 | right brow, outer to inner | 70+46 (outer tip: upper and lower edge meet) · 63 · 105 · 66 · 107+55 (inner tip) |
| 22-26 | left brow, inner to outer  | 336+285 · 296 · 334 · 293 · 300+276                                           |
| 27-30 | nose bridge, sellion to tip | 168 (between the eyes) · 197 · 195+5 · 4 (pronasale: the mesh's most forward point) |
| 31-35 | nostrils, right to left   | 98 (right alar base) · 97 · 2 (subnasale) · 326 · 327                          |
| 36-41 | right eye from the outer corner, upper lid then lower lid | 33 · 160+159 · 158+157 · 133 · 153 · 144     |
| 42-47 | left eye from the inner corner, upper lid then lower lid  | 362 · 385+384 · 387+386 · 263 · 373 · 380    |
| 48-59 | outer lip from the right corner, upper then lower | 61 · 40+39 · 37 (bow peak) · 0 · 267 · 270+269 · 291 · 321 · 405+314 · 17 · 181+84 · 91 |
| 60-67 | inner lip from the right corner, upper then lower | 78 · 81 · 13 · 311 · 308 · 402 · 14 · 178     |

The brow middle points follow the brow's upper edge (mesh row 70-63-105-66-107), as iBUG annotates them.
"""

from __future__ import annotations

import numpy as np

#: iBUG-68 point -> the one or two mesh vertices it is (the mean of)
MESH_TO_IBUG68: tuple[tuple[int, ...], ...] = (
    # jaw 0-16
    (127,),
    (234,),
    (93, 132),
    (132, 58),
    (58, 172),
    (136,),
    (150, 149),
    (176, 148),
    (152,),
    (377, 400),
    (378, 379),
    (365,),
    (397, 288),
    (288, 361),
    (361, 323),
    (454,),
    (356,),
    # right brow 17-21, left brow 22-26
    (70, 46),
    (63,),
    (105,),
    (66,),
    (107, 55),
    (336, 285),
    (296,),
    (334,),
    (293,),
    (300, 276),
    # nose bridge 27-30, nostrils 31-35
    (168,),
    (197,),
    (195, 5),
    (4,),
    (98,),
    (97,),
    (2,),
    (326,),
    (327,),
    # right eye 36-41, left eye 42-47
    (33,),
    (160, 159),
    (158, 157),
    (133,),
    (153,),
    (144,),
    (362,),
    (385, 384),
    (387, 386),
    (263,),
    (373,),
    (380,),
    # outer lip 48-59
    (61,),
    (40, 39),
    (37,),
    (0,),
    (267,),
    (270, 269),
    (291,),
    (321,),
    (405, 314),
    (17,),
    (181, 84),
    (91,),
    # inner lip 60-67
    (78,),
    (81,),
    (13,),
    (311,),
    (308,),
    (402,),
    (14,),
    (178,),
)

#: iBUG-68 point -> its mirror image (left/right swapped), for symmetry checks and flipping
IBUG68_MIRROR = np.array(
    list(range(16, -1, -1))
    + list(range(26, 16, -1))
    + [27, 28, 29, 30]
    + [35, 34, 33, 32, 31]
    + [45, 44, 43, 42, 47, 46]
    + [39, 38, 37, 36, 41, 40]
    + [54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55]
    + [64, 63, 62, 61, 60, 67, 66, 65]
)

#: iBUG index groups
JAW = np.arange(0, 17)
RIGHT_EYE, LEFT_EYE = np.arange(36, 42), np.arange(42, 48)
NOSE_BRIDGE_TOP = 27
#: points that move little with expression: eye corners, nose bridge and nostrils (pose and crop alignment)
RIGID = np.array([27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45])


def _mapping_matrix() -> np.ndarray:
    m = np.zeros((68, 468))
    for i, vertices in enumerate(MESH_TO_IBUG68):
        m[i, list(vertices)] = 1.0 / len(vertices)
    return m


MAPPING_MATRIX = _mapping_matrix()


def mesh_to_ibug68(mesh: np.ndarray) -> np.ndarray:
    """(..., 468, d) face-mesh points to (..., 68, d) iBUG points (vectorised over leading axes)."""
    mesh = np.asarray(mesh, dtype=np.float64)
    if mesh.shape[-2] != 468:
        raise ValueError(f"expected 468 mesh points, got {mesh.shape[-2]}")
    return np.matmul(MAPPING_MATRIX, mesh)  # BLAS; einsum is ten times slower per frame


def contour_fractions(points: np.ndarray, path: list[int]) -> np.ndarray:
    """Normalised arc length (0..1) of each vertex along a polyline of mesh vertices, averaged over frames
    ((frames, 468, 2) points): where each vertex sits on its contour."""
    xy = np.asarray(points)[..., path, :2]
    seg = np.linalg.norm(np.diff(xy, axis=-2), axis=-1)
    cum = np.concatenate([np.zeros(seg.shape[:-1] + (1,)), np.cumsum(seg, axis=-1)], axis=-1)
    return (cum / cum[..., -1:]).reshape(-1, len(path)).mean(axis=0)
