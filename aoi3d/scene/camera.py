"""A pinhole camera with a NeRF/OpenGL camera-to-world pose.

Conventions (the project-wide contract): ``c2w`` is a float64 4×4 rigid transform whose
rotation columns are the camera's x (right), y (up) and z (backwards) axes in world
coordinates; the camera looks along its −z axis. Pixel ``(u, v)`` has ``u`` growing to the
right and ``v`` growing downwards; the centre of pixel ``(i, j)`` is ``(i + 0.5, j + 0.5)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["RIGID_TOL", "Camera", "look_at"]

RIGID_TOL = 1e-6
"""Tolerance of :meth:`Camera.validate` on orthonormality and the last row of ``c2w``."""


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: pose ``c2w`` (4×4, OpenGL axes) and intrinsics in pixels."""

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        c2w = np.array(self.c2w, dtype=np.float64)
        if c2w.shape != (4, 4):
            raise ValueError(f"c2w must be 4×4, got shape {c2w.shape}")
        c2w.setflags(write=False)
        object.__setattr__(self, "c2w", c2w)
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value:
                raise ValueError(f"{name} must be an integer, got {value!r}")
            object.__setattr__(self, name, int(value))

    # -- identity ---------------------------------------------------------------------------
    def _key(self) -> tuple[Any, ...]:
        return (self.c2w.tobytes(), self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    # -- geometry ---------------------------------------------------------------------------
    @property
    def position(self) -> np.ndarray:
        """The camera centre in world coordinates, (3,)."""
        return self.c2w[:3, 3].copy()

    @property
    def rotation(self) -> np.ndarray:
        """The camera-to-world rotation, (3, 3); columns are the camera's x, y, z axes."""
        return self.c2w[:3, :3].copy()

    @property
    def camera_angle_x(self) -> float:
        """Horizontal field of view in radians (the NeRF ``camera_angle_x``)."""
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    def validate(self) -> None:
        """Raise ``ValueError`` unless the pose is finite and rigid and the intrinsics sane."""
        if not np.all(np.isfinite(self.c2w)):
            raise ValueError("c2w has non-finite entries")
        if np.max(np.abs(self.c2w[3] - (0.0, 0.0, 0.0, 1.0))) > RIGID_TOL:
            raise ValueError(f"c2w last row must be [0, 0, 0, 1], got {self.c2w[3].tolist()}")
        rot = self.c2w[:3, :3]
        ortho_err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
        if ortho_err > RIGID_TOL:
            raise ValueError(f"c2w rotation is not orthonormal (max |RᵀR − I| = {ortho_err:.3g})")
        if np.linalg.det(rot) < 0:
            raise ValueError("c2w rotation has determinant −1 (a reflection, not a rotation)")
        intrinsics = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in intrinsics):
            raise ValueError(f"intrinsics must be finite, got {intrinsics}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}×{self.height}")

    def pixel_rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixel coordinates ``(u, v)`` (any equal shapes): float64 origins and
        unit directions of shape ``u.shape + (3,)``."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        cam = np.stack(
            [(u - self.cx) / self.fx, -(v - self.cy) / self.fy, -np.ones_like(u)], axis=-1
        )
        dirs = cam @ self.c2w[:3, :3].T
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.c2w[:3, 3], dirs.shape).copy()
        return origins, dirs

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays through the pixel centres: float32 origins (H, W, 3), unit directions (H, W, 3)."""
        u, v = np.meshgrid(
            np.arange(self.width, dtype=np.float64) + 0.5,
            np.arange(self.height, dtype=np.float64) + 0.5,
        )
        origins, dirs = self.pixel_rays(u, v)
        return origins.astype(np.float32), dirs.astype(np.float32)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) → pixel coordinates (N, 2) as ``(u, v)`` and depth along the
        viewing axis (N,); depth ≤ 0 means behind the camera."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cam = (pts - self.c2w[:3, 3]) @ self.c2w[:3, :3]
        depth = -cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.cx + self.fx * cam[:, 0] / depth
            v = self.cy - self.fy * cam[:, 1] / depth
        return np.stack([u, v], axis=-1), depth

    # -- serialisation ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (``c2w`` as nested lists)."""
        return {
            "c2w": self.c2w.tolist(),
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Camera:
        """Inverse of :meth:`to_dict`; raises ``ValueError`` on missing keys."""
        missing = [k for k in ("c2w", "fx", "fy", "cx", "cy", "width", "height") if k not in data]
        if missing:
            raise ValueError(f"camera dict lacks {missing}")
        return cls(
            c2w=np.asarray(data["c2w"], dtype=np.float64),
            fx=data["fx"],
            fy=data["fy"],
            cx=data["cx"],
            cy=data["cy"],
            width=data["width"],
            height=data["height"],
        )


def look_at(
    eye: np.ndarray | tuple[float, float, float],
    target: np.ndarray | tuple[float, float, float],
    up: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> np.ndarray:
    """The OpenGL camera-to-world 4×4 pose of a camera at ``eye`` looking at ``target``."""
    eye_v = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye_v
    norm = np.linalg.norm(forward)
    if not norm > 0:
        raise ValueError("look_at: eye and target coincide")
    forward /= norm
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    rnorm = np.linalg.norm(right)
    if not rnorm > 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    right /= rnorm
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0] = right
    c2w[:3, 1] = true_up
    c2w[:3, 2] = -forward
    c2w[:3, 3] = eye_v
    return c2w
