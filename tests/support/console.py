"""The console's tests' truth frames and renders: flat images of one value, on the network
tests' camera."""

from __future__ import annotations

import numpy as np

from services.kit.codec import camera_to_pb, encode_frame, encode_png
from services.kit.pb import aoi3d_pb2 as pb
from tests.support.network import CAMERA


def image(value: int) -> np.ndarray:
    return np.full((CAMERA.height, CAMERA.width, 3), value, np.uint8)


def truth(t_ms: float, value: int) -> bytes:
    return encode_frame(camera_id=0, sequence=int(t_ms), generation_ms=t_ms, scene_time_ms=t_ms,
                        camera=CAMERA, image=encode_png(image(value)))


def render(decision_id: int, t_ms: float, value: int) -> bytes:
    pose, intr = camera_to_pb(CAMERA)
    return pb.Render(decision_id=decision_id, time_ms=t_ms, pose=pose, intrinsics=intr,
                     image=encode_png(image(value)), n_views=3, carry="fresh").SerializeToString()
