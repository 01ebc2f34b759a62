"""Hostile and restarted senders on the bus (issue 11, failures 1 and 2): each case froze or
blocked a service before; now the message is rejected and counted, or — a restarted
scheduler — recognised and followed at once."""

from __future__ import annotations

import io
import time
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient
from PIL import Image

from aoi3d.clock import SimClock
from aoi3d.scene import SceneDataset
from services.dispatcher.app import create_app as trainer_app
from services.kit.codec import PNG, encode_frame
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from tests.support.dispatcher import (
    KEYS,
    N_TRAIN,
    frame_payload,
    make_settings,
    metric,
    publish_frames,
)
from tests.support.waits import wait_for

U64_MAX = 2**64 - 1


@pytest.fixture
def dispatcher(dataset: SceneDataset) -> Iterator[tuple[TestClient, MemoryBus]]:
    bus = MemoryBus()
    # the clock is 10 s into the run (time scale 10: 100 s of sim time), so the decisions
    # below are in its past; the skew is 0.5 s × 10 = 5000 sim ms
    settings = make_settings()
    settings.common.epoch_s = time.time() - 10.0
    clock = SimClock(settings.common.epoch_s, settings.common.time_scale)
    app = trainer_app(settings, bus=bus, clock=clock, dataset=dataset)
    with TestClient(app) as c:
        yield c, bus


def decision(decision_id: int, time_ms: float, incarnation: int,
             refs: list[tuple[int, float]]) -> bytes:
    ids = list(range(1, N_TRAIN + 1))
    return pb.Decision(decision_id=decision_id, incarnation=incarnation, time_ms=time_ms,
                       camera_ids=ids, aoi_ms=[50.0] * len(ids),
                       selected=[pb.FrameRef(camera_id=c, generation_ms=g) for c, g in refs],
                       policy="all").SerializeToString()


def in_force(client: TestClient) -> tuple[int, float] | None:
    d = client.get("/status").json()["decision"]
    return None if d is None else (d["decision_id"], d["time_ms"])


def test_a_restarted_scheduler_is_followed_at_once(dispatcher, dataset: SceneDataset) -> None:
    client, bus = dispatcher
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision(777, 3000.0, incarnation=11, refs=[(1, 0.0)]))
    wait_for(lambda: in_force(client) == (777, 3000.0), what="the first scheduler's decision")
    # the scheduler restarts: a new incarnation numbering from 1 again
    bus.publish(KEYS.decision, decision(1, 3030.0, incarnation=22, refs=[(2, 0.0)]))
    wait_for(lambda: in_force(client) == (1, 3030.0), what="the restarted scheduler's decision")
    assert metric(client, "aoi3d_messages_rejected_total", 'reason="stale_decision"',
                  default=0.0) == 0.0


def test_decision_id_u64_max_does_not_freeze_the_trainer(dispatcher, dataset: SceneDataset) -> None:
    client, bus = dispatcher
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision(U64_MAX, 3000.0, incarnation=11, refs=[(1, 0.0)]))
    wait_for(lambda: in_force(client) == (U64_MAX, 3000.0), what="the poisoned decision")
    # the same scheduler goes on with its own small ids at later times: they are taken
    bus.publish(KEYS.decision, decision(5, 3030.0, incarnation=11, refs=[(2, 0.0)]))
    wait_for(lambda: in_force(client) == (5, 3030.0), what="a later decision after the poison")


def test_decisions_from_the_future_are_rejected_and_counted(dispatcher,
                                                            dataset: SceneDataset) -> None:
    client, bus = dispatcher
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision(1, 1e12, incarnation=11, refs=[(1, 0.0)]))
    wait_for(lambda: metric(client, "aoi3d_messages_rejected_total", 'reason="clock_skew"',
                            default=0.0) == 1.0, what="the future decision counted")
    bus.publish(KEYS.decision, decision(2, 3000.0, incarnation=11, refs=[(1, 0.0)]))
    wait_for(lambda: in_force(client) == (2, 3000.0), what="the next real decision")


def test_a_huge_png_is_rejected_before_it_is_decoded(dispatcher, dataset: SceneDataset) -> None:
    client, bus = dispatcher
    ds = dataset
    buf = io.BytesIO()
    Image.new("RGB", (4096, 4096)).save(buf, format="PNG")  # ~50 KB, 50 MB decoded
    cam = ds.cameras[1]
    big = type(cam)(c2w=cam.c2w, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
                    width=4096, height=4096)
    payload = encode_frame(camera_id=1, sequence=0, generation_ms=0.0, scene_time_ms=0.0,
                           camera=big, image=pb.Image(encoding=PNG, width=4096, height=4096,
                                                      data=buf.getvalue()))
    bus.publish(KEYS.edge_frame(1), payload)
    wait_for(lambda: metric(client, "aoi3d_messages_rejected_total", 'reason="image_size_mismatch"',
                            default=0.0) == 1.0, what="the huge frame counted")
    assert client.get("/status").json()["frames_received"] == 0
    bus.publish(KEYS.edge_frame(1), frame_payload(ds, 1, 0.0))  # a real frame still goes in
    wait_for(lambda: client.get("/status").json()["frames_received"] == 1)

