"""The observation of the frame-selection agent: the AoI vector, normalised, unknowns flagged.

The AoI Δ_n(t) of camera n is unbounded and unknown (NaN) until the camera's first frame is
delivered. The agent sees a float32 vector of length 2N:

- ``min(Δ_n / scale, 1)`` for known AoIs (≥ 0), ``1.0`` for unknown ones — "as stale as it
  gets": an AoI of ``scale_ms`` or more is treated as useless anyway;
- one flag per camera, ``1.0`` where the AoI is unknown, else ``0.0`` — so that "unknown" is
  explicit and never confused with "very old".

Both halves lie in [0, 1], which is the environment's observation space.

An agent may observe more of each camera (issue 25, item 3): ``features`` it was trained
with, whose per-camera values are fixed per rig and stored in its config, appended after the
two halves, one block of N per value (:func:`with_camera_features`). The one such feature
today is ``pose`` (:func:`pose_features`): where each camera looks from, relative to the
held-out view — the angle between the optical axes (/π) and the distance between the centres
(/ the largest), both in [0, 1].

An agent may also observe the expected lag L from the decision to its display (issue 40,
:func:`with_lag`): ``min(L / scale, 1)``, one more block of N equal values, appended last.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CAMERA_FEATURES", "encode_aoi", "obs_size", "pose_features",
           "with_camera_features", "with_lag"]

CAMERA_FEATURES = {"pose": ("pose_angle", "pose_distance")}
"""Per-camera features an agent may observe besides the AoI, and the values each adds per
camera (fixed per rig; measured in ``bench/state_features.py``, docs/ppo.md)."""


def obs_size(n_cameras: int, values_per_camera: int = 0) -> int:
    """Length of the encoded observation of ``n_cameras`` AoIs (2N), plus
    ``values_per_camera`` fixed values of each camera."""
    return (2 + values_per_camera) * n_cameras


def pose_features(c2w: np.ndarray, heldout_c2w: np.ndarray) -> np.ndarray:
    """(N, 2) per camera: the angle between its optical axis and the held-out camera's (/π)
    and the distance between their centres (/ the largest of the N), from camera-to-world
    poses (OpenGL axes: the camera looks along −z). Each value in [0, 1]."""
    poses = np.asarray(c2w, dtype=np.float64)
    held = np.asarray(heldout_c2w, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or held.shape != (4, 4):
        raise ValueError(f"need (N, 4, 4) camera poses and a (4, 4) held-out pose, got "
                         f"{poses.shape} and {held.shape}")
    axes = -poses[:, :3, 2] / np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True)
    axis = -held[:3, 2] / np.linalg.norm(held[:3, 2])
    angle = np.arccos(np.clip(axes @ axis, -1.0, 1.0)) / math.pi
    dist = np.linalg.norm(poses[:, :3, 3] - held[:3, 3], axis=1)
    far = float(dist.max())
    return np.stack([angle, dist / far if far > 0 else dist], axis=1)


def with_camera_features(obs: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The observation ``obs`` (2N) with fixed per-camera ``values`` (N, k) appended, value
    by value: ``[obs..., v_1 of cameras 1..N, ..., v_k of cameras 1..N]`` (float32)."""
    v = np.asarray(values, dtype=np.float64)
    n = obs.shape[-1] // 2
    if v.ndim != 2 or v.shape[0] != n:
        raise ValueError(f"camera features must be (N, k) with N = {n}, got {v.shape}")
    return np.concatenate([obs, v.T.reshape(-1).astype(np.float32)]).astype(np.float32)


def encode_aoi(aoi_ms: np.ndarray, scale_ms: float = 300.0) -> np.ndarray:
    """Encode the AoI vector (ms, NaN = unknown) as the agent's float32 observation (2N).

    ``[min(aoi/scale, 1) with unknown -> 1.0 ..., unknown flag 0/1 ...]``. A negative or
    infinite AoI, a non-vector or a non-positive scale raise ``ValueError``.
    """
    if not (isinstance(scale_ms, int | float) and math.isfinite(scale_ms) and scale_ms > 0):
        raise ValueError(f"scale_ms must be a finite number > 0, got {scale_ms!r}")
    aoi = np.asarray(aoi_ms, dtype=np.float64)
    if aoi.ndim != 1:
        raise ValueError(f"aoi_ms must be a 1-D vector (one AoI per camera), got {aoi.shape}")
    unknown = np.isnan(aoi)
    known = aoi[~unknown]
    if np.any(known < 0) or not np.all(np.isfinite(known)):
        raise ValueError(f"AoI must be finite and >= 0 ms (NaN = unknown), got {aoi_ms!r}")
    scaled = np.where(unknown, 1.0, np.minimum(np.where(unknown, 0.0, aoi) / scale_ms, 1.0))
    return np.concatenate([scaled, unknown.astype(np.float64)]).astype(np.float32)


def with_lag(obs: np.ndarray, n_cameras: int, lag_ms: float, scale_ms: float = 300.0
             ) -> np.ndarray:
    """The observation ``obs`` with the expected display lag appended: N copies of
    ``min(lag_ms / scale_ms, 1)`` (float32). A negative or non-finite lag raises
    ``ValueError``."""
    if not (isinstance(lag_ms, int | float) and math.isfinite(lag_ms) and lag_ms >= 0):
        raise ValueError(f"lag_ms must be a finite number >= 0, got {lag_ms!r}")
    if not (isinstance(scale_ms, int | float) and math.isfinite(scale_ms) and scale_ms > 0):
        raise ValueError(f"scale_ms must be a finite number > 0, got {scale_ms!r}")
    block = np.full(n_cameras, min(float(lag_ms) / scale_ms, 1.0), dtype=np.float32)
    return np.concatenate([np.asarray(obs, dtype=np.float32), block]).astype(np.float32)
