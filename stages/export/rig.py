"""The character's rig for the exported files: a root, a head joint at the head pivot, and an eye joint at the
centre of each eyeball when the character has eyes; and the eye rotations from gaze angles.

Eyes are found by material group name (``find_eyes``): a group whose name holds "eye" or a part of the eyeball
(sclera, iris, pupil, cornea) and a side ("left"/"L" or "right"/"R") and none of the words of the skin around the
eye (lid, lash, brow, socket, occlusion, tear, shadow); ICT FaceKit's ``M_EyeScleraLeft``, ``M_EyeIrisLeft``,
``M_EyePupilLeft`` (the embedded GLB) and its OBJs' ``M_ScleraLeft``, ``M_IrisLeft`` are the left eye. Sides are the
character's own (ARKit ``_L`` = the character's left = +x in glTF axes). The eye's centre is the least-squares
sphere through its sclera (or eyeball) vertices, else through all of its vertices: on ICT the sclera lies within
0.7 mm of a sphere of radius 14.4 mm.

Gaze (contract of the tracking and blend stages): (frames, 2, 2) degrees, [eye (0 = left, 1 = right)][yaw,
pitch] of the eyeball relative to the head, yaw > 0 towards the character's left, pitch > 0 up. In the rotation
convention of stages.geometry.rotations (R = Ry(yaw) Rx(pitch) Rz(roll), pitch > 0 tips the gaze down) the eye's
rotation is R = Ry(yaw) Rx(-pitch): ``gaze_euler`` returns those angles.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from stages.formats.gltf import HEAD_JOINT, Skeleton

ROOT_JOINT = "Root"
EYE_JOINTS = ("LeftEye", "RightEye")
_EYE_PART = re.compile(r"eye|sclera|iris|pupil|cornea", re.IGNORECASE)
_NOT_EYEBALL = re.compile(r"lid|lash|brow|socket|occlu|tear|shadow|wet|blend", re.IGNORECASE)
_LEFT = re.compile(r"left|(^|[^a-z])l$|(^|[_.\-\s])l([_.\-\s]|$)", re.IGNORECASE)
_RIGHT = re.compile(r"right|(^|[^a-z])r$|(^|[_.\-\s])r([_.\-\s]|$)", re.IGNORECASE)


@dataclass
class Eye:
    """One eyeball: its vertices, centre (the joint position) and radius."""

    side: int  # 0 = left, 1 = right
    vertices: np.ndarray
    center: np.ndarray
    radius: float


def eye_side(group_name: str) -> int | None:
    """0 (left), 1 (right) or None for a material group name (see the module docstring)."""
    if not _EYE_PART.search(group_name) or _NOT_EYEBALL.search(group_name):
        return None
    left, right = bool(_LEFT.search(group_name)), bool(_RIGHT.search(group_name))
    return 0 if left and not right else 1 if right and not left else None


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere through points: |p|^2 = 2 p.c + (r^2 - |c|^2) is linear in (c, r^2 - |c|^2)."""
    p = np.asarray(points, dtype=np.float64)
    a = np.c_[2 * p, np.ones(len(p))]
    solution, *_ = np.linalg.lstsq(a, (p * p).sum(axis=1), rcond=None)
    center = solution[:3]
    return center, float(np.sqrt(max(solution[3] + center @ center, 0.0)))


def find_eyes(neutral: np.ndarray, triangles: np.ndarray, triangle_groups, group_names: list[str]) -> list[Eye]:
    """The character's eyeballs (left first), from its material groups; [] when it has none or only one."""
    if triangle_groups is None:
        return []
    triangle_groups = np.asarray(triangle_groups)
    eyes = []
    for side in (0, 1):
        groups = [g for g, name in enumerate(group_names) if eye_side(name) == side]
        if not groups:
            return []
        vertices = np.unique(np.asarray(triangles)[np.isin(triangle_groups, groups)])
        shell = [g for g in groups if re.search(r"sclera|eyeball|ball", group_names[g], re.IGNORECASE)]
        fit_on = np.unique(np.asarray(triangles)[np.isin(triangle_groups, shell)]) if shell else vertices
        if len(fit_on) < 4:
            return []
        center, radius = fit_sphere(np.asarray(neutral)[fit_on])
        eyes.append(Eye(side, vertices, center, radius))
    return eyes


def character_skeleton(n_vertices: int, pivot, eyes: list[Eye]) -> Skeleton:
    """Root at the origin, Head at the pivot (every vertex but the eyeballs' follows it), an eye joint per eye."""
    names, parents = [ROOT_JOINT, HEAD_JOINT], [-1, 0]
    positions = [np.zeros(3), np.asarray(pivot, dtype=np.float64)]
    vertex_joint = np.full(n_vertices, 1, dtype=np.int64)
    for eye in eyes:
        names.append(EYE_JOINTS[eye.side])
        parents.append(1)
        positions.append(eye.center)
        vertex_joint[eye.vertices] = len(names) - 1
    return Skeleton(names, parents, np.asarray(positions), vertex_joint)


def gaze_euler(gaze_degrees: np.ndarray) -> np.ndarray:
    """(frames, 2, 3) radians (yaw, pitch, roll) per eye in the rotations convention, from (frames, 2, 2)
    degrees of gaze (yaw, pitch up): yaw unchanged, pitch negated, no roll."""
    gaze = np.radians(np.asarray(gaze_degrees, dtype=np.float64))
    return np.stack([gaze[..., 0], -gaze[..., 1], np.zeros_like(gaze[..., 0])], axis=-1)


def gaze_rotations(gaze_degrees: np.ndarray) -> np.ndarray:
    """(frames, 2, 4) unit quaternions (w, x, y, z) of each eye relative to the head."""
    from stages.geometry.rotations import euler_to_quat

    angles = gaze_euler(gaze_degrees)
    return euler_to_quat(angles[..., 0], angles[..., 1], angles[..., 2])
