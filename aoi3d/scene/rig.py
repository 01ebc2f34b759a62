"""The camera rig around the turbine: camera 0 is the held-out novel view, 1..N train.

The training cameras stand on an arc of :data:`ARC_SPAN_DEG` centred on the rotor's front
(azimuth −90°, i.e. the −y side), equally spaced in azimuth, with radius and height varying
slightly (deterministic, no RNG). Every camera looks at a point on the tower below the hub.
Camera 0 stands in the middle of the arc, halfway in azimuth between the two training cameras
nearest its centre, a little closer and higher than its neighbours.
"""

from __future__ import annotations

import math

import numpy as np

from aoi3d.scene.camera import Camera, look_at
from aoi3d.scene.turbine import SceneConfig

__all__ = [
    "ARC_CENTRE_DEG",
    "ARC_SPAN_DEG",
    "HELDOUT_ID",
    "HFOV_DEG",
    "LOOK_AT",
    "make_rig",
]

HELDOUT_ID = 0
ARC_CENTRE_DEG = -90.0
"""Azimuth (from +x, counter-clockwise) of the arc's centre: in front of the rotor."""
ARC_SPAN_DEG = 170.0
"""Azimuth span from the first to the last training camera."""
RADIUS = 4.0
HEIGHT = 1.55
LOOK_AT = np.array([0.0, 0.0, 1.3])
HFOV_DEG = 55.0
"""Horizontal field of view shared by all cameras."""


def _intrinsics(cfg: SceneConfig) -> dict[str, float | int]:
    focal = cfg.width / 2.0 / math.tan(math.radians(HFOV_DEG) / 2.0)
    return {
        "fx": focal,
        "fy": focal,
        "cx": cfg.width / 2.0,
        "cy": cfg.height / 2.0,
        "width": cfg.width,
        "height": cfg.height,
    }


def _camera(cfg: SceneConfig, azimuth_deg: float, radius: float, height: float) -> Camera:
    az = math.radians(azimuth_deg)
    eye = np.array([radius * math.cos(az), radius * math.sin(az), height])
    cam = Camera(c2w=look_at(eye, LOOK_AT), **_intrinsics(cfg))
    cam.validate()
    return cam


def make_rig(cfg: SceneConfig | None = None) -> list[Camera]:
    """``cfg.n_train + 1`` cameras; list index = camera id, id 0 is the held-out view."""
    cfg = cfg if cfg is not None else SceneConfig()
    n = cfg.n_train
    # Camera 0 halfway (in azimuth) between the two training cameras nearest the arc's centre.
    spacing = ARC_SPAN_DEG / (n - 1) if n > 1 else 20.0
    heldout_az = ARC_CENTRE_DEG + (spacing / 2.0 if n % 2 == 1 else 0.0)
    cams = [_camera(cfg, heldout_az, RADIUS - 0.2, HEIGHT + 0.1)]
    for k in range(n):
        frac = 0.5 if n == 1 else k / (n - 1)  # 0 … 1 along the arc
        azimuth = ARC_CENTRE_DEG - ARC_SPAN_DEG / 2.0 + ARC_SPAN_DEG * frac
        radius = RADIUS + 0.2 * math.sin(2.0 * math.pi * 1.5 * frac)
        height = HEIGHT + 0.15 * math.cos(2.0 * math.pi * 2.0 * frac)
        cams.append(_camera(cfg, azimuth, radius, height))
    return cams
