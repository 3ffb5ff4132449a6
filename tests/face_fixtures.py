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


# ----------------------------------------------------------------------------------------------- synthetic takes

#: texture patterns of the synthetic bilinear takes: more texture components than style and content dimensions,
#: so the texture alone determines both (the analysis reads the style from the texture by default)
N_PATTERNS = 8


def texture_patterns(size: tuple[int, int], n: int) -> np.ndarray:
    """n smooth, distinct grey-level patterns (n, h, w) over a texture image of ``size`` (w, h): products of
    low-frequency cosines."""
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w]
    freqs = [(1, 0), (0, 1), (1, 1), (2, 0), (0, 2), (2, 1), (1, 2), (2, 2), (3, 0), (0, 3)][:n]
    return np.stack([np.cos(np.pi * a * (xs + 0.5) / w) * np.cos(np.pi * b * (ys + 0.5) / h) for a, b in freqs]) * 40


def smooth_trajectory(rng, frames: int, dim: int, centre: np.ndarray, amplitude: float = 0.3) -> np.ndarray:
    """(frames, dim) smooth random content trajectory around ``centre`` (dim - 1,), whose first component is 1: the
    constant part of a face (mean shape and texture) is then itself bilinear, as the model's mean-face component
    assumes."""
    t = np.linspace(0, 1, frames)[:, None]
    freq, phase = rng.uniform(1, 3, (1, dim - 1)), rng.uniform(0, 2 * np.pi, (1, dim - 1))
    moving = np.asarray(centre) + amplitude * np.sin(2 * np.pi * freq * t + phase)
    return np.concatenate([np.ones((frames, 1)), moving], axis=1)


def bilinear_takes(
    n_styles: int = 3,
    takes_per_style: int = 3,
    frames: int = 30,
    style_spread: float = 1.0,
    content_spread: float = 0.3,
    seed: int = 0,
    expression_of=None,
):
    """A tracking artifact of synthetic takes whose faces are bilinear in style and content (Eq 4).

    Take r of style s says sentence "S{r}" with content trajectory c_r(t) (the same in every style, so the takes of a
    sentence form a set); its configuration y = e_s' W c_r(t) drives three shape modes (``face_modes``) and
    ``N_PATTERNS`` texture patterns painted on the face. The style shows in the texture only (the shape rows of W are
    the same for every style dimension), as the paper observes of real faces, so the takes of a sentence have the
    same mouth motion and align exactly. The texture is drawn with the triangulation of the shapes'
    Procrustes mean, the one the appearance model finds, so its warp recovers the painted texture. ``style_spread``
    scales how far the style vectors lie from their mean; the r-th takes' contents move around centres
    ``content_spread`` apart (far apart against the style spread: a take's nearest frames in another take of its
    own expression are further than the same speech in another expression).
    ``expression_of(s, r)`` names each take's expression field (default: the true style "E{s}").
    Returns (artifact view, true style per take).
    """
    from msflow.testing import artifact
    from stages.face.aam import apply_similarity, generalised_procrustes, texture_reference
    from stages.face.warp import PiecewiseAffineWarp, delaunay_triangles

    rng = np.random.default_rng(seed)
    styles = np.ones(n_styles) + style_spread * (np.eye(n_styles) - 1 / n_styles)
    w = rng.normal(size=(n_styles, 3, 3 + N_PATTERNS)) / np.sqrt(3 * n_styles)
    w[:, :, :3] = w[0, :, :3]  # the shape says the speech alone (styles sum to n_styles): exact DTW alignment
    angles = 2 * np.pi * np.arange(takes_per_style) / takes_per_style
    centres = content_spread * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    contents = [smooth_trajectory(rng, frames, 3, centre) for centre in centres]
    y = np.stack([np.einsum("i,ijk,fj->fk", styles[s], w, c) for s in range(n_styles) for c in contents])
    local = face_template() + np.einsum("tfm,mpd->tfpd", 0.15 * y[..., :3], face_modes())
    shapes = apply_similarity(local.reshape(-1, 68, 2), np.array([[22.0, 0.0, 32.0, 30.0]]))
    aligned = generalised_procrustes(shapes)[0]
    points, size = texture_reference(aligned.mean(0), 40)
    warp = PiecewiseAffineWarp(points, delaunay_triangles(points), size)
    base = face_texture(max(size))[: size[1], : size[0]]
    textures = base + np.tensordot(0.3 * y[..., 3:].reshape(-1, N_PATTERNS), texture_patterns(size, N_PATTERNS), 1)
    crops = []
    for shape, texture in zip(shapes, textures):
        drawn, covered = warp.draw_on_shape(warp.fill_outside(texture[None])[0], shape, (64, 64))
        crops.append(np.clip(np.round(np.where(covered, drawn, 90.0)), 0, 255).astype(np.uint8))
    labels = [f"s{s}_r{r}" for s in range(n_styles) for r in range(takes_per_style)]
    expression_of = expression_of or (lambda s, r: f"E{s}")
    fields = {
        f"s{s}_r{r}": {"expression": expression_of(s, r), "sentence": f"S{r}"}
        for s in range(n_styles)
        for r in range(takes_per_style)
    }
    arrays = {
        "landmarks": shapes.astype(np.float32),
        "crop_landmarks": shapes.astype(np.float32),
        "crops": np.stack(crops),
        "sequence": np.repeat(np.arange(len(labels)), frames).astype(np.int32),
    }
    meta = {"labels": labels, "fields": fields, "fps": 30.0, "landmark_scheme": "ibug68"}
    return artifact(arrays, meta), [s for s in range(n_styles) for _ in range(takes_per_style)]
