"""The metrics service's tests' images and messages (tests/services/test_metrics.py, the ledger
and the metrics core): a smooth truth that changes with time, noisy renders of it."""

from __future__ import annotations

import numpy as np

from aoi3d.scene.camera import Camera, look_at
from services.kit.codec import camera_to_pb, encode_frame, encode_png
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb

W, H = 24, 18
RUN = "test-metrics"
KEYS = Keys(RUN)
PERIOD_MS = 30.0


def _camera(width: int = W, height: int = H) -> Camera:
    return Camera(c2w=look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0, fy=20.0,
                  cx=width / 2, cy=height / 2, width=width, height=height)


def truth_image(gen_ms: float) -> np.ndarray:
    """A smooth image that differs from one generation time to the next."""
    yy, xx = np.mgrid[0:H, 0:W]
    phase = gen_ms / 100.0
    img = np.stack([0.5 + 0.4 * np.sin(xx / 3.0 + phase), 0.5 + 0.4 * np.cos(yy / 4.0 - phase),
                    (xx + yy) / (H + W)], axis=-1)
    return (img * 255 + 0.5).astype(np.uint8)


def noisy(img: np.ndarray, seed: int, sigma: float = 12.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(img + rng.normal(0, sigma, img.shape), 0, 255).astype(np.uint8)


def truth(gen_ms: float, *, camera_id: int = 0, image: np.ndarray | None = None) -> bytes:
    img = truth_image(gen_ms) if image is None else image
    cam = _camera(img.shape[1], img.shape[0])
    return encode_frame(camera_id=camera_id, sequence=int(gen_ms // PERIOD_MS),
                        generation_ms=gen_ms, scene_time_ms=gen_ms % 1000.0, camera=cam,
                        image=encode_png(img), send_ms=gen_ms)


def render(time_ms: float, image: np.ndarray, *, decision_id: int = 7, step: int = 1234,
           render_steps: int = 0, ready_ms: float | None = None) -> bytes:
    """A Render of the decision of ``time_ms``; ``render_steps``: the steps trained on its
    frames; ``ready_ms``: when it was ready (absent: the metrics service's clock says)."""
    pose, intr = camera_to_pb(_camera(image.shape[1], image.shape[0]))
    msg = pb.Render(decision_id=decision_id, time_ms=time_ms, pose=pose, intrinsics=intr,
                    image=encode_png(image), training_step=step, n_views=5, backend="grid",
                    render_steps=render_steps)
    if ready_ms is not None:
        msg.ready_ms = ready_ms
    return msg.SerializeToString()

