"""Head pose from 2D landmarks: ``cv2.solvePnP`` of the 68 points against a generic 3D face.

The 3D face is the 68 ICT FaceKit landmark vertices (cm, glTF head frame). A pinhole camera with square pixels,
principal point at the image centre and an assumed focal length (pixels) is the only camera model: the pose is
the rigid motion that best reprojects the 3D landmarks onto the tracked ones. OpenCV's camera frame (x right,
y down, z forward) is converted to the stages.geometry.rotations convention: glTF axes (x right, y up, z towards the
viewer), identity = the head facing the camera upright. With C = diag(1, -1, -1): R = C R_cv, t = C t_cv.
"""

from __future__ import annotations

import numpy as np

from stages.geometry.rotations import matrix_to_quat, quat_continuous

CV_TO_GLTF = np.diag([1.0, -1.0, -1.0])


def camera_matrix(width: float, height: float, focal_length: float | None = None) -> np.ndarray:
    """Pinhole intrinsics; the default focal length is the image width (about 53 degrees horizontal field)."""
    f = float(focal_length) if focal_length else float(width)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def solve_head_pose(
    landmarks: np.ndarray, face3d: np.ndarray, camera: np.ndarray, points: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame pose of the 3D face from (frames, 68, 2) image landmarks.

    Returns (rotation (frames, 4) unit quaternions, translation (frames, 3) in the 3D face's units, glTF camera
    axes, reprojection RMS (frames,) pixels). ``points`` selects the landmarks used (default all 68). Each frame
    starts the iterative solver from the previous frame's pose, which keeps the sequence on one solution
    branch (sequential by nature: one solvePnP per frame).
    """
    import cv2

    landmarks = np.asarray(landmarks, dtype=np.float64)
    idx = np.arange(68) if points is None else np.asarray(points)
    obj = np.ascontiguousarray(face3d[idx], dtype=np.float64)
    dist = np.zeros(4)
    n = len(landmarks)
    rot = np.zeros((n, 3, 3))
    trans = np.zeros((n, 3))
    rms = np.zeros(n)
    rvec = tvec = None
    for i in range(n):
        img = np.ascontiguousarray(landmarks[i, idx])
        if rvec is None:
            ok, rvec, tvec = cv2.solvePnP(obj, img, camera, dist, flags=cv2.SOLVEPNP_SQPNP)
            ok, rvec, tvec = cv2.solvePnP(
                obj, img, camera, dist, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
            )
        else:
            ok, rvec, tvec = cv2.solvePnP(
                obj, img, camera, dist, rvec.copy(), tvec.copy(), useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
            )
        r_cv, _ = cv2.Rodrigues(rvec)
        rot[i] = CV_TO_GLTF @ r_cv
        trans[i] = CV_TO_GLTF @ tvec.reshape(3)
        projected, _ = cv2.projectPoints(obj, rvec, tvec, camera, dist)
        rms[i] = np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - img) ** 2, axis=1)))
    return quat_continuous(matrix_to_quat(rot)), trans, rms


def project_face(face3d: np.ndarray, rotation: np.ndarray, translation: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """Image points (frames, P, 2) of 3D points (P, 3) under glTF-convention poses (inverse of solve_head_pose)."""
    from stages.geometry.rotations import quat_to_matrix

    r = quat_to_matrix(rotation)  # (frames, 3, 3)
    cam_gl = np.einsum("fij,pj->fpi", r, face3d) + np.asarray(translation)[:, None, :]
    cam_cv = cam_gl @ CV_TO_GLTF  # C is its own inverse and symmetric
    uvw = cam_cv @ camera.T
    return uvw[..., :2] / uvw[..., 2:3]


def openface_pose_to_gltf(euler_xyz: np.ndarray, translation_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenFace 2.0 pose columns to the stages.geometry.rotations convention.

    OpenFace: R = Rx(pose_Rx) Ry(pose_Ry) Rz(pose_Rz) acting on its head model, whose axes match OpenCV's
    camera when the head faces the camera (x right, y down, z away); pose_T in millimetres, camera axes. So
    R_gltf = C R C and t = C T / 10 (centimetres, the 3D face's units).
    """
    e = np.asarray(euler_xyz, dtype=np.float64)
    a, b, c = e[..., 0], e[..., 1], e[..., 2]
    one, zero = np.ones_like(a), np.zeros_like(a)
    rx = np.stack(
        [
            np.stack([one, zero, zero], -1),
            np.stack([zero, np.cos(a), -np.sin(a)], -1),
            np.stack([zero, np.sin(a), np.cos(a)], -1),
        ],
        -2,
    )
    ry = np.stack(
        [
            np.stack([np.cos(b), zero, np.sin(b)], -1),
            np.stack([zero, one, zero], -1),
            np.stack([-np.sin(b), zero, np.cos(b)], -1),
        ],
        -2,
    )
    rz = np.stack(
        [
            np.stack([np.cos(c), -np.sin(c), zero], -1),
            np.stack([np.sin(c), np.cos(c), zero], -1),
            np.stack([zero, zero, one], -1),
        ],
        -2,
    )
    r = CV_TO_GLTF @ (rx @ ry @ rz) @ CV_TO_GLTF
    t = np.asarray(translation_mm, dtype=np.float64) @ CV_TO_GLTF / 10.0
    return quat_continuous(matrix_to_quat(r)), t
