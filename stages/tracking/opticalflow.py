"""Pyramidal Lucas-Kanade tracking of the 68 points with a forward-backward check and a shape-model constraint.

Each frame: the points move by ``cv2.calcOpticalFlowPyrLK`` (Bouguet's pyramidal Lucas-Kanade) from the previous
frame; tracking them back again and comparing with where they started (forward-backward error, Kalal et al.
2010) flags points the flow lost. The shape is then projected onto the point distribution model (shape_model.py)
with the lost points weighing nothing, so they are predicted from the rest, and every point stays on a plausible
face shape (the paper's eigen-tracking, Sec. 6). The projected shape seeds the next frame.
"""

from __future__ import annotations

import numpy as np

from stages.tracking.shape_model import ShapeModel, fit_shape


class LucasKanadeTracker:
    """Sequential 68-point tracker on grayscale frames."""

    def __init__(
        self,
        *,
        window: int = 21,
        levels: int = 3,
        fb_threshold: float = 1.0,
        model: ShapeModel | None = None,
        model_noise: float = 0.02,
        min_good_fraction: float = 0.5,
    ):
        import cv2

        self.window = (int(window), int(window))
        self.levels = int(levels)
        self.criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        self.fb_threshold = fb_threshold
        self.base_model = model
        self.model: ShapeModel | None = None
        self.model_noise = model_noise
        self.min_good_fraction = min_good_fraction
        self.prev: np.ndarray | None = None
        self.points: np.ndarray | None = None

    def start(self, gray: np.ndarray, points: np.ndarray) -> None:
        """Begin at ``points`` (68, 2) on ``gray``; the shape model's mean becomes this shape."""
        self.prev = gray
        self.points = np.asarray(points, dtype=np.float64)
        self.model = self.base_model.with_mean(self.points) if self.base_model is not None else None

    def step(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Track into the next frame: (points (68, 2), good (68,) bool, forward-backward error (68,) px)."""
        import cv2

        p0 = self.points.astype(np.float32).reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            self.prev, gray, p0, None, winSize=self.window, maxLevel=self.levels, criteria=self.criteria
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            gray, self.prev, p1, None, winSize=self.window, maxLevel=self.levels, criteria=self.criteria
        )
        fb = np.linalg.norm((back - p0).reshape(-1, 2), axis=1).astype(np.float64)
        good = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < self.fb_threshold)
        moved = p1.reshape(-1, 2).astype(np.float64)
        moved = np.where(good[:, None], moved, self.points)  # lost points stay until the model places them
        if self.model is not None:
            moved, _ = fit_shape(self.model, moved, good.astype(np.float64), noise=self.model_noise)
        self.prev = gray
        self.points = moved
        return moved, good, np.where(np.isfinite(fb), fb, np.inf)

    def is_lost(self, good: np.ndarray) -> bool:
        return good.mean() < self.min_good_fraction
