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


class PoseSolver:
    """Head pose frame after frame, each ``cv2.solvePnP`` starting from the previous frame's pose (which keeps the
    sequence on one solution branch); blocks of frames in turn give the same poses as one whole sequence."""

    def __init__(self, face3d: np.ndarray, camera: np.ndarray, points: np.ndarray | None = None):
        self.idx = np.arange(68) if points is None else np.asarray(points)
        self.obj = np.ascontiguousarray(face3d[self.idx], dtype=np.float64)
        self.camera = camera
        self.rvec = self.tvec = None
        self.last_quat: np.ndarray | None = None

    def solve(self, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rotation (frames, 4), translation (frames, 3), reprojection RMS (frames,)) of the next frames."""
        import cv2

        landmarks = np.asarray(landmarks, dtype=np.float64)
        dist = np.zeros(4)
        n = len(landmarks)
        rot, trans, rms = np.zeros((n, 3, 3)), np.zeros((n, 3)), np.zeros(n)
        for i in range(n):
            img = np.ascontiguousarray(landmarks[i, self.idx])
            if self.rvec is None:
                self.rvec, self.tvec = first_pose(self.obj, img, self.camera)
            _, self.rvec, self.tvec = cv2.solvePnP(
                self.obj,
                img,
                self.camera,
                dist,
                self.rvec.copy(),
                self.tvec.copy(),
                useExtrinsicGuess=True,
                flags=cv2.SOLVEPNP_ITERATIVE,
            )
            r_cv, _ = cv2.Rodrigues(self.rvec)
            rot[i] = CV_TO_GLTF @ r_cv
            trans[i] = CV_TO_GLTF @ self.tvec.reshape(3)
            projected, _ = cv2.projectPoints(self.obj, self.rvec, self.tvec, self.camera, dist)
            rms[i] = np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - img) ** 2, axis=1)))
        return self._continuous(matrix_to_quat(rot)), trans, rms

    def _continuous(self, q: np.ndarray) -> np.ndarray:
        """Signs flipped so consecutive quaternions, across blocks too, lie in one hemisphere."""
        if not len(q):
            return q
        lead = [] if self.last_quat is None else [self.last_quat]
        q = quat_continuous(np.concatenate([lead, q]) if lead else q)[len(lead) :]
        self.last_quat = q[-1]
        return q


def first_pose(obj: np.ndarray, img: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV (rvec, tvec) of a take's first frame, with no pose to start from: SQPnP (a global optimum), or,
    where the points span too little of the normalised image for it (a small face under a long lens, as an
    estimated focal length gives a distant head), OpenCV's iterative solve from its own start."""
    import cv2

    dist = np.zeros(4)
    try:
        _, rvec, tvec = cv2.solvePnP(obj, img, camera, dist, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        _, rvec, tvec = cv2.solvePnP(obj, img, camera, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    return rvec, tvec


def solve_head_pose(
    landmarks: np.ndarray, face3d: np.ndarray, camera: np.ndarray, points: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame pose of the 3D face from (frames, 68, 2) image landmarks.

    Returns (rotation (frames, 4) unit quaternions, translation (frames, 3) in the 3D face's units, glTF camera
    axes, reprojection RMS (frames,) pixels). ``points`` selects the landmarks used (default all 68). Each frame
    starts the iterative solver from the previous frame's pose (``PoseSolver``; sequential by nature).
    """
    return PoseSolver(face3d, camera, points).solve(landmarks)


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
