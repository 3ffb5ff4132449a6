"""Face regions shared by the region-by-region retarget fit and the retargeting evaluation.

A region pairs the iBUG-68 landmarks that show it with the morph targets that move it. Morphs are assigned by
name (fnmatch patterns on ARKit / ICT FaceKit names, compared by ``morph_key``: case and separators ignored, so
``Mouth_Smile_L`` and ``mouth-smile.L`` are ICT's ``mouthSmile_L``); a character with other names gives its own
patterns in the stage params. The order matters for the fit: the jaw is fitted before the lips, so the lips fit
only what the jaw did not explain (a dropped jaw and rounded lips both part the lips; only the jaw moves the chin).
"""

from __future__ import annotations

import fnmatch

import numpy as np

from stages.formats.live_link import morph_key

#: iBUG-68 landmark groups
JAW_LINE = tuple(range(0, 17))
CHIN = tuple(range(4, 13))
BROWS = tuple(range(17, 27))
NOSE = tuple(range(27, 36))
EYES = tuple(range(36, 48))
RIGHT_EYE = tuple(range(36, 42))  # the subject's right eye (image left)
LEFT_EYE = tuple(range(42, 48))
LIPS = tuple(range(48, 68))
INNER_LIPS = tuple(range(60, 68))
#: eye corners and nose: they barely move with expression (pose and similarity alignment)
RIGID = (27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45)

#: landmark regions the evaluation reports
EVAL_REGIONS: dict[str, tuple[int, ...]] = {"mouth": LIPS, "eyes": EYES, "brows": BROWS, "jaw": JAW_LINE}

#: morph region by name: first matching pattern wins (lower-cased fnmatch); None = not observable in landmarks
MORPH_REGION_PATTERNS: tuple[tuple[str, str | None], ...] = (
    ("eyelook*", "gaze"),
    ("pupil*", None),
    ("tongue*", None),
    ("eye*", "eyes"),
    ("brow*", "brows"),
    ("jaw*", "jaw"),
    ("mouth*", "mouth"),
    ("cheekpuff*", "mouth"),
    ("cheek*", "cheeks"),
    ("nose*", "cheeks"),
)


def names_matching(names: list[str], patterns: list[str]) -> np.ndarray:
    """Boolean mask of the names matching any fnmatch pattern, both compared by ``morph_key``."""
    keys = [morph_key(p) for p in patterns]
    return np.array([any(fnmatch.fnmatchcase(morph_key(n), k) for k in keys) for n in names], dtype=bool)


def morph_region(name: str) -> str | None:
    """The region a morph target moves, from its name (``jawOpen`` -> jaw, ``eyeLookIn_L`` -> gaze); None when the
    name matches no region or the region is not observable from landmarks (pupils, tongue)."""
    key = morph_key(name)
    for pattern, region in MORPH_REGION_PATTERNS:
        if fnmatch.fnmatchcase(key, pattern):
            return region
    return None


def find_morph(names: list[str], stem: str) -> int | None:
    """Index of the morph whose name is ``stem`` whatever its case and separators (``jawOpen``, ``JawOpen``,
    ``jaw_open``, ``Jaw-Open``), or None."""
    want = morph_key(stem)
    for i, name in enumerate(names):
        if morph_key(name) == want:
            return i
    return None


def region_masks(names: list[str], regions: list[str]) -> np.ndarray:
    """(regions, morphs) boolean: which morph belongs to which region (by ``morph_region``)."""
    assigned = [morph_region(n) for n in names]
    return np.array([[a == r for a in assigned] for r in regions], dtype=bool).reshape(len(regions), len(names))


def find_side_morph(names: list[str], stem: str, side: str) -> int | None:
    """Index of the morph ``stem`` on one side ("L" or "R"): ``eyeBlink_L`` (ICT) or ``eyeBlinkLeft`` (ARKit)."""
    index = find_morph(names, f"{stem}_{side}")
    return index if index is not None else find_morph(names, stem + ("Left" if side == "L" else "Right"))
