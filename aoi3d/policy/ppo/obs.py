"""The observation of the frame-selection agent: the AoI vector, normalised, unknowns flagged.

The AoI Δ_n(t) of camera n is unbounded and unknown (NaN) until the camera's first frame is
delivered. The agent sees a float32 vector of length 2N:

- ``min(Δ_n / scale, 1)`` for known AoIs (≥ 0), ``1.0`` for unknown ones — "as stale as it
  gets": an AoI of ``scale_ms`` or more is treated as useless anyway;
- one flag per camera, ``1.0`` where the AoI is unknown, else ``0.0`` — so that "unknown" is
  explicit and never confused with "very old".

Both halves lie in [0, 1], which is the environment's observation space.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["encode_aoi", "obs_size"]


def obs_size(n_cameras: int) -> int:
    """Length of the encoded observation of ``n_cameras`` AoIs (2N)."""
    return 2 * n_cameras


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
