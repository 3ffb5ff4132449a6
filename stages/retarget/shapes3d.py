"""The performer's face in 3D, in the head's own frame (pose removed), from the tracker's FaceMesh.

FaceMesh gives 468 points per frame: x, y in image pixels and a relative depth z in pixels (negative towards the
camera). The 68 iBUG points are means of mesh vertices (``stages.tracking.landmarks68``), so the same table gives
them depth. Axes are turned into the head frame of the rest of the project (glTF: x to the viewer's right, y up,
z towards the viewer): (x, -y, -z).

Pose removal is a generalised Procrustes analysis on the rigid points (eye corners, nose): each frame is carried by
a 3D similarity (Umeyama) onto a reference, the reference is the mean of the aligned frames, three rounds. Units
are the reference's inter-ocular distance (IOD = 1). The tracked head rotation (solvePnP of a generic face on the
2D landmarks) would also remove the pose; on the CREMA-D takes it leaves the rigid points scattered 1.3% IOD RMS
against 0.8% for the mesh's own 3D alignment, so the latter is used.
"""

from __future__ import annotations

import numpy as np

from stages.retarget.regions import RIGID

#: FaceMesh image axes (x right, y down, z away from the viewer) to the head frame's (x right, y up, z to viewer)
MESH_TO_HEAD_AXES = np.array([1.0, -1.0, -1.0])


def mesh_landmarks(mesh: np.ndarray) -> np.ndarray:
    """(frames, 468, 3) FaceMesh points to (frames, 68, 3) iBUG points in right-handed head axes (pixels)."""
    from stages.tracking.landmarks68 import mesh_to_ibug68

    return mesh_to_ibug68(mesh) * MESH_TO_HEAD_AXES


def similarity_align(points: np.ndarray, reference: np.ndarray, rigid=RIGID) -> np.ndarray:
    """Every frame of ``points`` (frames, P, d) carried onto ``reference`` (P, d), or onto its own frame of
    ``reference`` (frames, P, d), by the least-squares similarity of its rigid points (Umeyama 1991), vectorised
    over frames."""
    points = np.asarray(points, np.float64)
    rigid = list(rigid)
    source = points[:, rigid]
    target = np.broadcast_to(np.asarray(reference, np.float64)[..., rigid, :], source.shape)
    mu_s, mu_t = source.mean(axis=1), target.mean(axis=1)
    s, t = source - mu_s[:, None], target - mu_t[:, None]
    u, sigma, vt = np.linalg.svd(np.einsum("fpi,fpj->fij", t, s))
    d = np.ones(sigma.shape)
    d[:, -1] = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)
    rotation = u @ (d[..., None] * vt)
    scale = (sigma * d).sum(axis=1) / np.maximum((s**2).sum(axis=(1, 2)), 1e-300)
    moved = np.einsum("fij,fpj->fpi", rotation, points - mu_s[:, None]) * scale[:, None, None]
    return moved + mu_t[:, None]


def inter_ocular(points: np.ndarray) -> np.ndarray:
    """Outer eye corner distance (iBUG 36-45) of (..., 68, d) shapes."""
    points = np.asarray(points, np.float64)
    return np.linalg.norm(points[..., 45, :] - points[..., 36, :], axis=-1)


def remove_pose(points: np.ndarray, rigid=RIGID, rounds: int = 3) -> np.ndarray:
    """Generalised Procrustes on the rigid points: (frames, 68, d) shapes in one head frame, reference IOD = 1,
    centred on the reference's rigid points."""
    points = np.asarray(points, np.float64)
    reference = points[0]
    for _ in range(max(rounds, 1)):
        aligned = similarity_align(points, reference, rigid)
        reference = aligned.mean(axis=0)
        reference = (reference - reference[list(rigid)].mean(axis=0)) / inter_ocular(reference)
    return similarity_align(points, reference, rigid)


def head_frame_shapes(mesh: np.ndarray, extra_vertices: tuple[int, ...] = ()) -> np.ndarray:
    """The tracked FaceMesh as (frames, 68, 3) iBUG shapes, pose removed, IOD units; ``extra_vertices`` (mesh
    vertex ids) follow as points 68, 69, ..., carried by the same per-frame alignment."""
    shapes = mesh_landmarks(mesh)
    if extra_vertices:
        extra = np.asarray(mesh, np.float64)[:, list(extra_vertices)] * MESH_TO_HEAD_AXES
        shapes = np.concatenate([shapes, extra], axis=1)
    return remove_pose(shapes)


def undo_perspective(mesh: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """FaceMesh points (frames, P, 3): image x, y and relative depth z in pixels, with the perspective of a
    pinhole ``camera`` (3, 3) taken out, up to one scale per frame: a point at depth D = T (1 + z / f) (T the
    head's distance, f the focal length in pixels) lies at X = (x - c_x) D / f, so (x - c_x)(1 + z / f) is X
    times f / T, the same factor for every point of the frame (which the pose removal's similarity absorbs)."""
    mesh = np.asarray(mesh, np.float64)
    camera = np.asarray(camera, np.float64)
    focal, centre = camera[0, 0], camera[:2, 2]
    stretch = 1.0 + mesh[..., 2:3] / focal
    return np.concatenate([(mesh[..., :2] - centre) * stretch, mesh[..., 2:3]], axis=-1)


def with_focal(camera: np.ndarray, focal: float) -> np.ndarray:
    """A copy of the pinhole ``camera`` (3, 3) with focal length ``focal`` (pixels; inf: no perspective)."""
    out = np.array(camera, np.float64, copy=True)
    out[0, 0] = out[1, 1] = focal
    return out


#: focal lengths ``estimate_focal`` tries, as multiples of the tracked one (inf: no perspective, FaceMesh as it is)
FOCAL_MULTIPLES = (*np.geomspace(0.25, 16.0, 13), np.inf)


def rigid_scatter(shapes: np.ndarray, rigid=RIGID) -> float:
    """RMS distance (IOD) of the rigid points of (frames, 68, 3) shapes from their mean after pose removal: how far
    the frames are from one rigid head."""
    aligned = remove_pose(shapes, rigid)[:, list(rigid)]
    return float(np.sqrt(((aligned - aligned.mean(axis=0)) ** 2).sum(axis=-1).mean()))


def estimate_focal(
    mesh: np.ndarray, camera: np.ndarray, multiples=FOCAL_MULTIPLES, max_frames: int = 600
) -> tuple[float, np.ndarray]:
    """The focal length (pixels; inf: none) whose perspective removal (``undo_perspective``) leaves a take's rigid
    points (eye corners, nose) most rigid over its frames, with the scatter per multiple of ``camera``'s focal
    length tried (``rigid_scatter``). A pinhole's perspective changes the rigid points' image distances as the
    head turns, so the right focal length, taken out, leaves them one rigid shape; a wrong one leaves a scatter
    that grows with the pose. The frame width is a webcam's; cropped footage (a talking head cut out of a wider
    frame) was filmed with a longer lens relative to the crop (tracking estimates its own with this, on a take's
    first frames: ``stream.calibrate_focal``). At most ``max_frames`` frames, evenly spread; a tie
    with tracking's focal length (a still head) keeps it."""
    mesh = np.asarray(mesh, np.float64)
    mesh = mesh[np.isfinite(mesh).all(axis=(1, 2))]  # tracking fills its gaps; a frame without a face says nothing
    camera = np.asarray(camera, np.float64)
    if len(mesh) < 2:
        return float(camera[0, 0]), np.full(len(multiples), np.nan)
    if len(mesh) > max_frames:
        mesh = mesh[np.linspace(0, len(mesh) - 1, max_frames).round().astype(int)]
    scatter = np.empty(len(multiples))
    for i, multiple in enumerate(multiples):
        scatter[i] = rigid_scatter(mesh_landmarks(undo_perspective(mesh, with_focal(camera, camera[0, 0] * multiple))))
    best = int(np.argmin(scatter))
    tracked = np.flatnonzero(np.isclose(np.asarray(multiples, np.float64), 1.0))
    if tracked.size and scatter[tracked[0]] <= scatter[best] * (1 + 1e-6) + 1e-12:
        best = int(tracked[0])  # where the data cannot tell (a still head), tracking's focal length stays
    return float(camera[0, 0] * multiples[best]), scatter


def front_view(points: np.ndarray) -> np.ndarray:
    """Head-frame points (..., 3) seen from the front in image convention (x right, y down): (x, -y)."""
    points = np.asarray(points, np.float64)
    return np.stack([points[..., 0], -points[..., 1]], axis=-1)
