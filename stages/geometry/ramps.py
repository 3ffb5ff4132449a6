"""Ramps from 0 to 1, shared by whatever eases one value into another (keyframes, segment joins, held gaps)."""

from __future__ import annotations

import numpy as np


def smoothstep(u: np.ndarray) -> np.ndarray:
    """C1 ramp from 0 (u <= 0) to 1 (u >= 1), slope 1.5 at its centre: 3u^2 - 2u^3."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)
