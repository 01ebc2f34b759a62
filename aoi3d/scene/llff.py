"""LLFF poses (the DyNeRF layout's ``poses_bounds.npy``) ↔ the project's OpenGL cameras, and
the boxes their depth bounds imply. The conventions are set out in :mod:`aoi3d.scene.dynerf`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from aoi3d.scene.camera import Camera

__all__ = [
    "LLFF_TO_OPENGL",
    "ROTATION_TOL",
    "aabb_depth_bounds",
    "frusta_aabb",
    "llff_to_opengl",
    "opengl_to_llff",
]

ROTATION_TOL = 1e-3

LLFF_TO_OPENGL = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""``P`` with ``R_opengl = R_llff · P``: LLFF [down, right, back] → OpenGL [right, up, back]."""


def _nearest_rotation(rot: np.ndarray, what: str) -> np.ndarray:
    u, _, vt = np.linalg.svd(rot)
    nearest = u @ vt
    if np.linalg.det(nearest) < 0:
        raise ValueError(f"{what}: rotation has determinant −1 (a reflection, not a rotation)")
    err = float(np.max(np.abs(nearest - rot)))
    if err > ROTATION_TOL:
        raise ValueError(f"{what}: not a rotation (max deviation {err:.3g} > {ROTATION_TOL})")
    return nearest


def llff_to_opengl(pose: np.ndarray, what: str = "pose") -> np.ndarray:
    """LLFF 3×4 (or 3×5) ``[R | t (| hwf)]`` with axes [down, right, back] → OpenGL 4×4 c2w."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape not in ((3, 4), (3, 5)):
        raise ValueError(f"{what}: an LLFF pose is 3×4 or 3×5, got shape {pose.shape}")
    if not np.all(np.isfinite(pose[:, :4])):
        raise ValueError(f"{what}: pose has non-finite entries")
    c2w = np.eye(4)
    c2w[:3, :3] = _nearest_rotation(pose[:, :3], what) @ LLFF_TO_OPENGL
    c2w[:3, 3] = pose[:, 3]
    return c2w


def opengl_to_llff(c2w: np.ndarray) -> np.ndarray:
    """OpenGL 4×4 c2w [right, up, back] → LLFF 3×4 ``[R | t]`` with axes [down, right, back]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return np.concatenate([c2w[:3, :3] @ LLFF_TO_OPENGL.T, c2w[:3, 3:4]], axis=1)


def _frustum_corners(camera: Camera, near: float, far: float) -> np.ndarray:
    """The 8 corners (8, 3) of the camera's frustum between depths ``near`` and ``far``."""
    u = np.array([0.0, camera.width, 0.0, camera.width])
    v = np.array([0.0, 0.0, camera.height, camera.height])
    cam = np.stack([(u - camera.cx) / camera.fx, -(v - camera.cy) / camera.fy, -np.ones(4)], 1)
    world = cam @ camera.c2w[:3, :3].T  # depth 1 along the viewing axis
    depths = np.array([near, far])[:, None, None]
    return (camera.c2w[:3, 3] + depths * world[None]).reshape(-1, 3)


def frusta_aabb(cameras: Sequence[Camera], near: Sequence[float] | np.ndarray,
                far: Sequence[float] | np.ndarray) -> np.ndarray:
    """The smallest axis-aligned box (2, 3) holding each camera's frustum between its near and
    far depth (depth = distance along the viewing axis, as LLFF bounds are): every point a
    camera sees within its bounds lies inside. Generous for forward-facing rigs (it includes
    the far plane's footprint), which is what a box-bounded field with a background needs."""
    if not (len(cameras) == len(near) == len(far)) or not cameras:
        raise ValueError("frusta_aabb needs one near and one far bound per camera (≥ 1 camera)")
    corners = np.concatenate(
        [_frustum_corners(c, n, f) for c, n, f in zip(cameras, near, far, strict=True)]
    )
    return np.stack([corners.min(axis=0), corners.max(axis=0)])


def aabb_depth_bounds(camera: Camera, aabb: np.ndarray) -> tuple[float, float]:
    """LLFF ``(near, far)`` of a box seen from ``camera``: the depth range of its 8 corners,
    with near at least 1e-3 × far (a camera inside the box)."""
    lo, hi = np.asarray(aabb, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    depth = (corners - camera.c2w[:3, 3]) @ -camera.c2w[:3, 2]
    far = float(depth.max())
    if far <= 0:
        raise ValueError("the box is behind the camera; pass explicit bounds")
    return max(float(depth.min()), 1e-3 * far), far
