"""The background every backend shares: a lat-long environment map of the ray direction.

Outside the scene box the turbine scene depends on the ray direction only (sky above, distant
ground below the horizon), so a ray that leaves the box sees ``sigmoid(env(d))``, where
``env`` is a (rows, columns, 3) map over polar angle (row 0 at the zenith of ``up_axis``, the
last row at the nadir) and azimuth (columns wrap around), sampled bilinearly.
"""

from __future__ import annotations

import math

import torch

from aoi3d.field import native

__all__ = ["latlong_background"]


def latlong_background(env: torch.Tensor, dirs: torch.Tensor, up_axis: int) -> torch.Tensor:
    """Colour in [0, 1] (R, 3) of unit directions ``dirs`` (R, 3) from the raw lat-long map
    ``env`` (rows ≥ 2, columns, 3); differentiable with respect to ``env``."""
    fused = native.latlong_background(env, dirs, up_axis)
    if fused is not None:
        return fused
    rows, cols = env.shape[:2]
    a, b = (up_axis + 1) % 3, (up_axis + 2) % 3
    polar = torch.acos(dirs[:, up_axis].clamp(-1.0, 1.0)) / math.pi  # 0 at zenith, 1 at nadir
    azimuth = (torch.atan2(dirs[:, b], dirs[:, a]) / (2 * math.pi)) % 1.0
    r = polar * (rows - 1)
    r0 = r.floor().clamp(0, rows - 2)
    fr = (r - r0)[:, None]
    r0 = r0.long()
    col = azimuth * cols
    c0f = col.floor()
    fc = (col - c0f)[:, None]
    c0 = c0f.long() % cols
    c1 = (c0 + 1) % cols
    top = env[r0, c0] * (1 - fc) + env[r0, c1] * fc
    bottom = env[r0 + 1, c0] * (1 - fc) + env[r0 + 1, c1] * fc
    return torch.sigmoid(top * (1 - fr) + bottom * fr)
