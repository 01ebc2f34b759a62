"""A pose's camera axes (:data:`CONVENTIONS`) → aoi3d's (OpenGL), and a quaternion → 4×4."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CONVENTIONS", "convert_pose", "quaternion_matrix"]

CONVENTIONS = ("optical", "opengl", "body")
"""Axes of a pose's camera frame: ``optical`` — ROS's camera optical frame (x right, y down, z
forward: REP 103, what ``image_raw`` is published in); ``opengl`` — aoi3d's own (x right, y up,
looking along −z); ``body`` — a ROS body/link frame (x forward, y left, z up)."""

_OPTICAL_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
_BODY_TO_GL = np.array([[0.0, 0.0, -1.0, 0.0],
                        [-1.0, 0.0, 0.0, 0.0],
                        [0.0, 1.0, 0.0, 0.0],
                        [0.0, 0.0, 0.0, 1.0]], dtype=np.float64)


def convert_pose(c2w: np.ndarray, convention: str) -> np.ndarray:
    """A camera-to-world transform whose camera axes follow ``convention`` → aoi3d's (OpenGL)."""
    c2w = np.asarray(c2w, dtype=np.float64).reshape(4, 4)
    if convention == "opengl":
        return c2w.copy()
    if convention == "optical":
        return c2w @ _OPTICAL_TO_GL
    if convention == "body":
        return c2w @ _BODY_TO_GL
    raise ValueError(f"unknown pose convention {convention!r}; one of {', '.join(CONVENTIONS)}")


def quaternion_matrix(position: list[float], orientation: list[float]) -> np.ndarray:
    """4×4 from a position and a unit quaternion ``(x, y, z, w)`` (ROS's order)."""
    x, y, z, w = (float(v) for v in orientation)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(n) and n > 1e-9):
        raise ValueError(f"orientation {orientation} is not a rotation (norm {n})")
    x, y, z, w = x / n, y / n, z / n, w / n
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [float(v) for v in position]
    return m
