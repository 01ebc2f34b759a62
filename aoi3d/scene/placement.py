"""The camera rig around the turbine: camera 0 is the held-out novel view, 1..N train.

The training cameras stand on an arc centred on the rotor's front (azimuth −90°, i.e. the −y
side), equally spaced in azimuth, with radius and height varying slightly (deterministic, no
RNG). Camera 0 stands in the middle of the arc, halfway in azimuth between the two training
cameras nearest its centre, a little closer and higher than its neighbours. Two framings
(:attr:`SceneConfig.framing`):

- ``site`` — a 170° arc, 55° field of view, every camera looking at a point on the tower below
  the hub: the whole turbine with its ground; the blades are a few per cent of the pixels.
- ``rotor`` — a 60° forward-facing arc (as DyNeRF's rig), 30° field of view, every camera
  looking at the hub: a close-up in which the blades are a large share of the pixels, so that
  the age of a frame shows in its pixels (the experiments' scene).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypedDict

import numpy as np

from aoi3d.scene.camera import Camera, look_at
from aoi3d.scene.turbine import HUB_CENTRE, SceneConfig

__all__ = [
    "ARC_CENTRE_DEG",
    "FRAMING",
    "HELDOUT_ID",
    "Framing",
    "place_cameras",
]

HELDOUT_ID = 0
ARC_CENTRE_DEG = -90.0
"""Azimuth (from +x, counter-clockwise) of the arc's centre: in front of the rotor."""


@dataclass(frozen=True)
class Framing:
    """The geometry of one framing: arc span (first to last training camera, degrees), arc
    radius, camera height, the point every camera looks at, and the horizontal field of view
    shared by all cameras."""

    arc_span_deg: float
    radius: float
    height: float
    look_at: tuple[float, float, float]
    hfov_deg: float


FRAMING: dict[str, Framing] = {
    "site": Framing(arc_span_deg=170.0, radius=4.0, height=1.55, look_at=(0.0, 0.0, 1.3),
                    hfov_deg=55.0),
    "rotor": Framing(arc_span_deg=60.0, radius=4.0, height=1.6,
                     look_at=(float(HUB_CENTRE[0]), float(HUB_CENTRE[1]), float(HUB_CENTRE[2])),
                     hfov_deg=30.0),
}


class _Intrinsics(TypedDict):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


def _intrinsics(cfg: SceneConfig, hfov_deg: float) -> _Intrinsics:
    focal = cfg.width / 2.0 / math.tan(math.radians(hfov_deg) / 2.0)
    return {
        "fx": focal,
        "fy": focal,
        "cx": cfg.width / 2.0,
        "cy": cfg.height / 2.0,
        "width": cfg.width,
        "height": cfg.height,
    }


def _camera(cfg: SceneConfig, frame: Framing, azimuth_deg: float, radius: float,
            height: float) -> Camera:
    az = math.radians(azimuth_deg)
    eye = np.array([radius * math.cos(az), radius * math.sin(az), height])
    cam = Camera(c2w=look_at(eye, np.asarray(frame.look_at)), **_intrinsics(cfg, frame.hfov_deg))
    cam.validate()
    return cam


def place_cameras(cfg: SceneConfig | None = None) -> list[Camera]:
    """``cfg.n_train + 1`` cameras; list index = camera id, id 0 is the held-out view."""
    cfg = cfg if cfg is not None else SceneConfig()
    frame = FRAMING[cfg.framing]
    n = cfg.n_train
    span = frame.arc_span_deg
    # Camera 0 halfway (in azimuth) between the two training cameras nearest the arc's centre.
    spacing = span / (n - 1) if n > 1 else 20.0
    heldout_az = ARC_CENTRE_DEG + (spacing / 2.0 if n % 2 == 1 else 0.0)
    cams = [_camera(cfg, frame, heldout_az, frame.radius - 0.2, frame.height + 0.1)]
    for k in range(n):
        frac = 0.5 if n == 1 else k / (n - 1)  # 0 … 1 along the arc
        azimuth = ARC_CENTRE_DEG - span / 2.0 + span * frac
        radius = frame.radius + 0.2 * math.sin(2.0 * math.pi * 1.5 * frac)
        height = frame.height + 0.15 * math.cos(2.0 * math.pi * 2.0 * frac)
        cams.append(_camera(cfg, frame, azimuth, radius, height))
    return cams
