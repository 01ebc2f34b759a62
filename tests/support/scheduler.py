"""The scheduler's tests' scaffolding (tests/services/test_scheduler.py and the tests that drive a
scheduler the same way): a wall clock the test sets, delivered frames, the decisions on the
bus, a harness that moves the clock and returns the decision taken."""

from __future__ import annotations

import threading

import numpy as np
from fastapi.testclient import TestClient

from aoi3d.scene.camera import Camera, look_at
from services.kit.codec import decode_decision, encode_frame, encode_png
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from tests.support.waits import wait_for

W, H = 16, 12
RUN = "test-sched"
KEYS = Keys(RUN)
N_CAMERAS = 4
PERIOD_MS = 30.0


class ManualWall:
    """A wall clock the test sets; with epoch 0 and time scale 1, sim ms = wall s × 1000."""

    def __init__(self, sim_ms: float = 0.0) -> None:
        self._lock = threading.Lock()
        self._wall_s = sim_ms / 1000.0

    def set_ms(self, sim_ms: float) -> None:
        with self._lock:
            self._wall_s = sim_ms / 1000.0

    def __call__(self) -> float:
        with self._lock:
            return self._wall_s


def _camera() -> Camera:
    return Camera(c2w=look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0, fy=20.0, cx=W / 2,
                  cy=H / 2, width=W, height=H)
IMAGE = encode_png(np.full((H, W, 3), 128, dtype=np.uint8))


def frame(camera_id: int, gen_ms: float, delivery_ms: float, *, sequence: int | None = None,
          camera: Camera | None = None, image: pb.Image = IMAGE) -> bytes:
    seq = int(gen_ms // PERIOD_MS) if sequence is None else sequence
    return encode_frame(camera_id=camera_id, sequence=seq, generation_ms=gen_ms,
                        scene_time_ms=gen_ms, camera=camera or _camera(), image=image,
                        send_ms=gen_ms, delivery_ms=delivery_ms)


def decisions(bus: MemoryBus) -> list[pb.Decision]:
    return [decode_decision(p) for p in bus.messages(KEYS.decision)]


class Harness:
    def __init__(self, client: TestClient, bus: MemoryBus, wall: ManualWall) -> None:
        self.client, self.bus, self.wall = client, bus, wall

    def decide_at(self, t_ms: float) -> pb.Decision:
        """Move the clock to ``t_ms`` and return the decision taken there."""
        before = len(decisions(self.bus))
        self.wall.set_ms(t_ms)
        wait_for(lambda: len(decisions(self.bus)) > before)
        last = decisions(self.bus)[-1]
        assert last.time_ms == t_ms
        return last

    def put(self, key: str, payload: bytes) -> None:
        self.bus.publish(key, payload)

