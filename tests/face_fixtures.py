"""Shared data for the face-analysis tests (aam, bilinear, edit): a synthetic iBUG-68 face with known modes, and the
CREMA-D takes tracked once per test session (FaceMesh) with the stages run on them, cached across test modules."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLIPS = {"neutral": "NEU", "happy": "HAP", "angry": "ANG", "disgust": "DIS", "fear": "FEA", "sad": "SAD"}


# ----------------------------------------------------------------------------------------------- synthetic


def face_template() -> np.ndarray:
    """A frontal iBUG-68 face (y down), eye centres at (-0.4, -0.25) and (0.4, -0.25)."""
    pts = np.zeros((68, 2))
    pts[0:17, 0] = -0.9 * np.cos(np.linspace(0, np.pi, 17))
    pts[0:17, 1] = -0.2 + 1.1 * np.abs(np.sin(np.linspace(0, np.pi, 17))) ** 0.8
    arch = 0.05 * np.sin(np.linspace(0, np.pi, 5))
    pts[17:22] = np.c_[np.linspace(-0.75, -0.15, 5), -0.45 - arch]
    pts[22:27] = np.c_[np.linspace(0.15, 0.75, 5), -0.45 - arch]
    pts[27:31] = np.c_[np.zeros(4), np.linspace(-0.3, 0.15, 4)]
    pts[31:36] = np.c_[np.linspace(-0.2, 0.2, 5), 0.25 + 0.03 * np.cos(np.linspace(-1.5, 1.5, 5))]
    eye = np.pi - np.arange(6) * np.pi / 3
    for start, cx in ((36, -0.4), (42, 0.4)):
        pts[start : start + 6] = np.c_[cx + 0.15 * np.cos(eye), -0.25 - 0.06 * np.sin(eye)]
    lip = np.pi - np.arange(12) * np.pi / 6
    pts[48:60] = np.c_[0.25 * np.cos(lip), 0.55 - 0.1 * np.sin(lip)]
    inner = np.pi - np.arange(8) * np.pi / 4
    pts[60:68] = np.c_[0.18 * np.cos(inner), 0.55 - 0.04 * np.sin(inner)]
    return pts


def face_modes() -> np.ndarray:
    """Three deformation modes (3, 68, 2): jaw open, smile, brow raise."""
    jaw = np.zeros((68, 2))
    jaw[3:14, 1] = np.sin(np.linspace(0, np.pi, 11)) * 0.3
    jaw[[56, 57, 58, 65, 66, 67], 1] = 0.25
    smile = np.zeros((68, 2))
    smile[[48, 60], :] = [-0.08, -0.06]
    smile[[54, 64], :] = [0.08, -0.06]
    brow = np.zeros((68, 2))
    brow[17:27, 1] = -0.12
    return np.stack([jaw, smile, brow])


def random_similarity(rng, n: int) -> np.ndarray:
    """(n, 4) [scale, angle, tx, ty] typical of faces in a 128-pixel crop."""
    return np.c_[rng.uniform(30, 45, n), rng.uniform(-0.3, 0.3, n), rng.uniform(50, 78, n), rng.uniform(50, 78, n)]


def synthetic_faces(n: int = 40, seed: int = 0, noise: float = 0.0):
    """Shapes (n, 68, 2) = similarity(template + coefficients @ modes) with known coefficients (n, 3)."""
    from stages.face.aam import apply_similarity

    rng = np.random.default_rng(seed)
    coef = rng.normal(0, 1, (n, 3)) * np.array([0.5, 0.3, 0.2])
    local = face_template() + np.einsum("fm,mpd->fpd", coef, face_modes())
    local = local + rng.normal(0, noise, local.shape)
    similarity = random_similarity(rng, n)
    return apply_similarity(local, similarity), coef, similarity, local


def face_texture(size: int = 128) -> np.ndarray:
    """A smooth grey-level pattern (size, size) float32 to paint on faces."""
    ys, xs = np.mgrid[0:size, 0:size] / size
    return (120 + 60 * np.sin(6 * xs) * np.cos(5 * ys) + 40 * xs).astype(np.float32)


# ----------------------------------------------------------------------------------------------- real data


@cache
def tracked(*labels: str):
    """FaceMesh tracking of CREMA-D 1001 takes, as an artifact view (cached for the session)."""
    from msflow.testing import run_stage
    from stages.tracking import FaceMesh

    videos = {label: ROOT / "data" / "crema-d" / f"1001_DFA_{CLIPS[label]}_XX.flv" for label in labels}
    return run_stage(FaceMesh, {}, {"videos": videos}).view()


def training_tracks():
    return tracked("neutral", "happy", "angry")


@cache
def aam_run():
    from msflow.testing import run_stage
    from stages.face.aam import AamPca

    return run_stage(AamPca, {}, {"tracks": training_tracks()})


@cache
def bilinear_run(align: str = "audio"):
    from msflow.testing import run_stage
    from stages.face.bilinear import BilinearFit

    return run_stage(BilinearFit, {"align": align}, {"aam": aam_run(), "tracks": training_tracks()})


@cache
def edit_run():
    from msflow.testing import run_stage
    from stages.face.edit import ExpressionEdit

    return run_stage(ExpressionEdit, {}, {"model": bilinear_run(), "aam": aam_run(), "tracks": tracked("sad")})
