"""The character's identity fitted to the performer (optional, ``GltfCharacter`` param ``fit_identity``).

A retarget transfers deformation, not identity, so by default the character keeps its own face. For a digital
double, or to measure the animation's absolute landmark error without the two faces' different proportions, the
character's identity shapes (ICT FaceKit has ten) can move its neutral face towards the performer's:

    min over c of  sum_p || S(N_p + sum_i c_i D_ip) - R_p ||^2  +  ridge * e * ||c||^2

with R (68, 3) the performer's rest face (the mean of the closed-mouth frames of the tracked FaceMesh, pose
removed, in the head frame: ``shapes3d.head_frame_shapes``), N the character's neutral landmark vertices, D_i its
identity shapes there, S a 3D similarity (the performer's head frame to the character's; Umeyama 1991), p over the brows, eyes, nose and lips (iBUG 17-67: FaceMesh's face contour follows the
silhouette, not the jaw bone), and e the identity shapes' mean landmark energy (so ``ridge`` is unit-free). Both are solved
together by Gauss-Newton (the similarity linearised as scale, rotation vector and translation, applied to the
performer's face so that c stays linear; a few rounds). Solving them in turn does not do: with the similarity
fitted on the rigid points while c moves them too, the two steps pursue different objectives and drift apart;
fitted on the same points, the steps agree but converge slowly (c found to 0.4 of a known mix in 100 rounds).
"""

from __future__ import annotations

import numpy as np

#: the landmarks the identity is fitted on: brows, nose, eyes and lips (iBUG 17-67)
IDENTITY_POINTS = tuple(range(17, 68))


def performer_rest_face(mesh: np.ndarray) -> np.ndarray:
    """The performer's rest face (68, 3) in the head frame, IOD units: the mean of the closed-mouth frames of a
    tracked FaceMesh (frames, 468, 3)."""
    from stages.retarget.face_measures import rest_frames
    from stages.retarget.shapes3d import front_view, head_frame_shapes

    shapes = head_frame_shapes(np.asarray(mesh, np.float64))
    return shapes[rest_frames(front_view(shapes))].mean(axis=0)


def fit_identity(
    rest: np.ndarray, neutral: np.ndarray, identities: np.ndarray, ridge: float = 0.1, rounds: int = 20
) -> np.ndarray:
    """Identity coefficients c (I,) that bring ``neutral`` (68, 3) + sum_i c_i ``identities`` (I, 68, 3) closest
    to ``rest`` (68, 3) up to a 3D similarity (the module docstring's problem), by Gauss-Newton on c and the
    similarity together."""
    from stages.retarget.shapes3d import similarity_align

    rest, neutral, identities = (np.asarray(a, np.float64) for a in (rest, neutral, identities))
    points = list(IDENTITY_POINTS)
    basis = identities[:, points].reshape(len(identities), -1).T  # (3P, I)
    penalty = np.r_[np.full(len(identities), ridge * np.mean((basis**2).sum(axis=0))), np.zeros(7)]
    moved = similarity_align(rest[None], neutral, points)[0]  # the performer's face in the character's frame
    c = np.zeros(len(identities))
    for _ in range(max(rounds, 1)):
        a = np.concatenate([basis, -similarity_jacobian(moved[points])], axis=1)
        b = (moved - neutral)[points].reshape(-1)
        solution = np.linalg.solve(a.T @ a + np.diag(penalty), a.T @ b)
        c, step = solution[: len(identities)], solution[len(identities) :]
        moved = apply_small_similarity(moved, step)
        if np.abs(step).max() < 1e-10:
            break
    return c


def similarity_jacobian(points: np.ndarray) -> np.ndarray:
    """d(points)/d(log scale, rotation vector, translation) at the identity similarity: (3P, 7)."""
    p = len(points)
    rotation = np.stack([np.cross(np.eye(3)[k], points) for k in range(3)], axis=-1)  # (P, 3, 3)
    translation = np.broadcast_to(np.eye(3), (p, 3, 3))
    return np.concatenate([points[..., None], rotation, translation], axis=-1).reshape(3 * p, 7)


def apply_small_similarity(points: np.ndarray, step: np.ndarray) -> np.ndarray:
    """points (P, 3) under exp(step[0]) R(step[1:4]) x + step[4:7] (R: Rodrigues' rotation of that vector)."""
    import cv2

    rotation, _ = cv2.Rodrigues(np.asarray(step[1:4], np.float64))
    return np.exp(step[0]) * points @ rotation.T + step[4:7]
