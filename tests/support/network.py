"""Delivered frames as the network service's tests make them: one camera, a grey image."""

from __future__ import annotations

import numpy as np

from aoi3d.scene import Camera, look_at
from services.kit.codec import encode_frame, encode_png

W, H = 24, 18


def _camera() -> Camera:
    return Camera(c2w=look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0, fy=20.0,
                  cx=W / 2, cy=H / 2, width=W, height=H)
CAMERA = _camera()
IMAGE = encode_png(np.full((H, W, 3), 128, dtype=np.uint8))


def frame(camera_id: int, gen_ms: float, *, sequence: int = 0) -> bytes:
    return encode_frame(camera_id=camera_id, sequence=sequence, generation_ms=gen_ms,
                        scene_time_ms=gen_ms % 1000, send_ms=gen_ms, camera=CAMERA, image=IMAGE)

