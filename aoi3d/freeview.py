"""Seeing the scene from anywhere: a free-view pose checked, the camera it makes, and the
pure geometry and colours of the 3D viewer (services/viewer).

One check of a free-view pose (:func:`check_pose`), used by the dispatcher's REST
(``GET /render.png?c2w=…``) and by the reconstruction worker's Zenoh query alike: 16 finite
numbers, a rigid transform (orthonormal rotation, determinant +1, last row 0 0 0 1), and a
camera centre within :data:`MAX_DISTANCE_DIAGONALS` box diagonals of the scene box's centre.
Poses are NeRF/OpenGL camera-to-world matrices, row-major, as in ``transforms.json``
(:mod:`aoi3d.scene.camera`): the camera looks along its −z axis, y up.

The viewer (viser, like nerfstudio's) speaks OpenCV axes (z forward, y down) and quaternions
``wxyz``; :func:`viser_pose` and :func:`c2w_from_viser` convert. :func:`aoi_colour` is the
colour of a camera's AoI at the decision in force (green fresh, yellow at Γ, red at 2Γ and
beyond). Numpy only: no I/O, no framework.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence

import numpy as np

from aoi3d.scene.camera import Camera

__all__ = [
    "MAX_DISTANCE_DIAGONALS",
    "MAX_VIEW_SIDE",
    "PoseError",
    "aoi_colour",
    "c2w_from_viser",
    "check_pose",
    "check_size",
    "free_camera",
    "frustum_fov_aspect",
    "matrix_to_wxyz",
    "parse_c2w",
    "viser_pose",
    "wxyz_to_matrix",
]

MAX_DISTANCE_DIAGONALS = 10.0
"""A free-view camera's centre may lie at most this many scene-box diagonals from the box's
centre (further away the box is a few pixels: a typo, not a view)."""
RIGID_TOL = 1e-3
"""Tolerance on the rotation's orthonormality and the last row (a pose typed with 4-6
decimals passes; a scaled or sheared one does not)."""
MAX_VIEW_SIDE = 1024
"""Largest width or height of a free-view render (the worker's default limit)."""

_GL_TO_CV = np.diag([1.0, -1.0, -1.0])
"""OpenGL camera axes (x right, y up, looking along −z) to OpenCV's (x right, y down, +z)."""


class PoseError(ValueError):
    """A free-view pose or size that cannot be rendered; the message says why (a 4xx)."""


def parse_c2w(text: str | Sequence[float]) -> np.ndarray:
    """The 4×4 matrix of 16 numbers (a string separated by commas or spaces, or a sequence),
    row-major; :class:`PoseError` unless there are exactly 16 finite numbers."""
    if isinstance(text, str):
        parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise PoseError("c2w must be 16 numbers separated by commas (row-major 4x4, "
                            "OpenGL axes as in transforms.json)") from None
    else:
        values = [float(v) for v in text]
    if len(values) != 16:
        raise PoseError(f"c2w must be 16 numbers (row-major 4x4), got {len(values)}")
    c2w = np.asarray(values, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(c2w)):
        raise PoseError("c2w must be 16 finite numbers (no NaN or infinity)")
    return c2w


def check_pose(c2w: np.ndarray | str | Sequence[float], aabb: np.ndarray | Sequence[float], *,
               max_distance_diagonals: float = MAX_DISTANCE_DIAGONALS) -> np.ndarray:
    """``c2w`` (4×4, or 16 numbers) if a camera can stand there, else :class:`PoseError`:
    16 finite numbers, a rigid transform, a centre within ``max_distance_diagonals`` box
    diagonals of the centre of ``aabb`` ((2, 3) or 6 values: min x y z, max x y z)."""
    m = parse_c2w(c2w) if isinstance(c2w, str) else parse_c2w(np.asarray(c2w).ravel().tolist())
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOL):
        raise PoseError(f"c2w is not a rigid transform: its last row must be 0 0 0 1, got "
                        f"{' '.join(f'{v:g}' for v in m[3])}")
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > RIGID_TOL:
        raise PoseError(f"c2w is not a rigid transform: its rotation is not orthonormal "
                        f"(|RᵀR − I| = {err:.3g}; scale and shear are not allowed)")
    if np.linalg.det(r) < 0:
        raise PoseError("c2w is not a rigid transform: its rotation is a reflection "
                        "(determinant −1)")
    box = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
    centre, diagonal = box.mean(axis=0), float(np.linalg.norm(box[1] - box[0]))
    distance = float(np.linalg.norm(m[:3, 3] - centre))
    limit = max_distance_diagonals * diagonal
    if distance > limit:
        raise PoseError(f"the camera is {distance:.3g} from the scene box's centre, beyond "
                        f"{limit:.3g} ({max_distance_diagonals:g} box diagonals)")
    return m


def check_size(width: int, height: int, max_side: int = MAX_VIEW_SIDE) -> tuple[int, int]:
    """``(width, height)`` if each is 8..``max_side`` pixels, else :class:`PoseError`."""
    for name, v in (("width", width), ("height", height)):
        if not 8 <= int(v) <= max_side:
            raise PoseError(f"{name} must be 8..{max_side} pixels, got {v}")
    return int(width), int(height)


def free_camera(c2w: np.ndarray, width: int, height: int, like: Camera | None = None,
                fov_y: float | None = None) -> Camera:
    """A pinhole camera at ``c2w`` of ``width``×``height`` pixels, square pixels, centred
    principal point; its vertical field of view ``fov_y`` (radians) or, by default, that of
    ``like`` (the held-out camera), else 50°."""
    if fov_y is None:
        fov_y = 2.0 * math.atan(like.height / (2.0 * like.fy)) if like is not None \
            else math.radians(50.0)
    if not 0.0 < fov_y < math.pi:
        raise PoseError(f"the field of view must be in (0, 180) degrees, got "
                        f"{math.degrees(fov_y):g}")
    f = height / (2.0 * math.tan(fov_y / 2.0))
    return Camera(c2w=c2w, fx=f, fy=f, cx=width / 2.0, cy=height / 2.0, width=width,
                  height=height)


# --------------------------------------------------------------------------- the viewer
def matrix_to_wxyz(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) of rotation matrix ``r`` (3×3)."""
    r = np.asarray(r, dtype=np.float64)
    t = np.trace(r)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    out = np.asarray(q, dtype=np.float64)
    out /= np.linalg.norm(out)
    return out if out[0] >= 0 else -out


def wxyz_to_matrix(wxyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """The rotation matrix (3×3) of quaternion ``wxyz`` (normalised first)."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def viser_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``(wxyz, position)`` of ``camera`` in the viewer's OpenCV axes (a frustum's pose)."""
    return matrix_to_wxyz(camera.rotation @ _GL_TO_CV), camera.position


def frustum_fov_aspect(camera: Camera) -> tuple[float, float]:
    """The vertical field of view (radians) and the aspect (width / height) of ``camera``."""
    return 2.0 * math.atan(camera.height / (2.0 * camera.fy)), camera.width / camera.height


def c2w_from_viser(wxyz: Sequence[float] | np.ndarray,
                   position: Sequence[float] | np.ndarray) -> np.ndarray:
    """The OpenGL camera-to-world matrix (4×4) of a viewer camera at ``wxyz``, ``position``
    (OpenCV axes): the inverse of :func:`viser_pose`."""
    c2w = np.eye(4)
    c2w[:3, :3] = wxyz_to_matrix(wxyz) @ _GL_TO_CV
    c2w[:3, 3] = np.asarray(position, dtype=np.float64)
    return c2w


_STOPS = ((0.0, (46, 204, 64)), (0.5, (255, 220, 0)), (1.0, (230, 30, 30)))
"""AoI / (2 Γ) → colour: green, yellow at Γ, red at 2 Γ."""


def aoi_colour(aoi_ms: float, gamma_ms: float | None) -> tuple[int, int, int]:
    """The colour of a camera whose frame is ``aoi_ms`` old at the decision in force: green
    when fresh, yellow at the MAT threshold Γ ``gamma_ms``, red at 2 Γ and beyond (no Γ — a
    policy without one —: 100 ms stands in). Grey for an unknown AoI (NaN, never delivered)."""
    if aoi_ms is None or not math.isfinite(aoi_ms):
        return (128, 128, 128)
    g = gamma_ms if gamma_ms is not None and math.isfinite(gamma_ms) and gamma_ms > 0 else 100.0
    t = min(1.0, max(0.0, aoi_ms / (2.0 * g)))
    for (t0, c0), (t1, c1) in itertools.pairwise(_STOPS):
        if t <= t1:
            u = (t - t0) / (t1 - t0)
            r, g_, b_ = (round(a + (b - a) * u) for a, b in zip(c0, c1, strict=True))
            return (r, g_, b_)
    return _STOPS[-1][1]
