"""The ingest service on the in-memory bus (issue 31): every bad input is a counted rejection
with its reason in Prometheus (``aoi3d_messages_rejected_total{reason}``, like every service's,
and ``aoi3d_ingest_rejected_total{camera,reason}``), losses and clamps have their series, the
service never stops taking good frames, and ``GET /status`` shows the cameras."""

from __future__ import annotations

import time
from functools import partial

import numpy as np
from fastapi.testclient import TestClient

from aoi3d.rigfile import rig_from_dict
from services import ros
from services.ingest.app import create_app
from services.ingest.settings import Settings
from services.kit.codec import decode_frame
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.settings import CommonSettings
from tests.support.ingest import C2W, GID, OPTICAL, H, W, rig_doc
from tests.support.metrics import total
from tests.support.timeouts import timeout_scale
from tests.support.waits import wait_for

SCALE = timeout_scale()
RGB = np.random.default_rng(3).integers(0, 255, (H, W, 3), dtype=np.uint8)
KEYS = Keys("t")


metric = partial(total, default=0.0)
"""The sum of a series' samples whose labels include the given ones (0 when none)."""


def wait(check, what: str, timeout_s: float = 5.0):
    return wait_for(check, timeout_s, what=what, every_s=0.02)


class Robot:
    """Puts ROS samples on the bus as an rmw_zenoh robot (its clock: the edge's)."""

    def __init__(self, bus: MemoryBus) -> None:
        self.bus = bus
        self.fmt = ros.KeyFormat()
        self.seq: dict[str, int] = {}

    def put(self, topic: str, ros_type: str, msg=None, *, payload: bytes | None = None,
            seq: int | None = None, attachment: bytes | None = b"", key: str | None = None):
        if attachment == b"":  # the robot's own: the next sequence number (or the one given)
            n = self.seq.get(topic, 0) + 1 if seq is None else seq
            self.seq[topic] = max(n, self.seq.get(topic, 0))
            attachment = ros.build_attachment(n, time.time_ns(), GID)
        self.bus.put(key or self.fmt.key(topic, ros_type),
                     ros.encode_cdr(msg, ros_type) if payload is None else payload, attachment)

    def frame(self, stamp: float | None = None, **kw) -> None:
        stamp = time.time() if stamp is None else stamp
        self.put("/cam1/camera_info", ros.CAMERA_INFO,
                 ros.camera_info_msg(stamp, "c", 20.0, 20.0, W / 2, H / 2, W, H))
        self.put("/cam1/pose", ros.POSE_STAMPED, ros.pose_stamped_msg(stamp, "w", C2W @ OPTICAL))
        self.put("/cam1/image_raw", ros.IMAGE, ros.image_msg(stamp, "c", RGB), **kw)


def bad_samples(robot: Robot) -> dict[str, callable]:
    """One bad sample per reason."""
    now = time.time
    img = ros.IMAGE

    def enc(encoding):
        m = ros.image_msg(now(), "c", RGB)
        m.encoding = encoding
        return m

    def stepped():
        m = ros.image_msg(now(), "c", RGB)
        m.step = W * 3 + 5
        return m

    good = ros.encode_cdr(ros.image_msg(now(), "c", RGB), img)
    big = ros.encode_cdr(ros.image_msg(now(), "c", np.zeros((200, 200, 3), np.uint8)), img)

    def lose():  # a gap of 4 in the sequence numbers, then a good frame
        robot.frame(seq=robot.seq["/cam1/image_raw"] + 5)

    return {
        "unknown_encoding": lambda: robot.put("/cam1/image_raw", img, enc("yuv422")),
        "bad_cdr": lambda: robot.put("/cam1/image_raw", img, payload=good[:len(good) // 3]),
        "image_mismatch": lambda: robot.put("/cam1/image_raw", img, stepped()),
        "too_large": lambda: robot.put("/cam1/image_raw", img, payload=big),
        "stamp_future": lambda: robot.frame(now() + 3.0),
        "stamp_stale": lambda: robot.frame(now() - 100.0),
        "stamp_invalid": lambda: robot.put("/cam1/image_raw", img, ros.image_msg(0.0, "c", RGB)),
        "no_pose": lambda: robot.put("/cam2/image_raw", img, ros.image_msg(now(), "c", RGB)),
        "bad_attachment": lambda: robot.put("/cam1/image_raw", img, ros.image_msg(now(), "c",
                                                                                  RGB),
                                            attachment=b"\x00" * 5),
        "type_hash_mismatch": lambda: robot.put(
            "/cam1/image_raw", img, ros.image_msg(now(), "c", RGB),
            key=robot.fmt.key("/cam1/image_raw", img, "RIHS01_" + "ab" * 32)),
        "sequence_replayed": lambda: robot.put("/cam1/image_raw", img,
                                               ros.image_msg(now(), "c", RGB), seq=1),
        "lost": lose,
    }


def test_every_bad_input_is_a_counted_rejection_and_good_frames_go_on() -> None:
    doc = rig_doc(max_image_bytes=64 * 1024)
    doc["cameras"].append({"name": "cam2b", "image": "/cam2/image_raw",
                           "intrinsics": {"camera_info": "/cam1/camera_info"},
                           "pose": {"topic": "/nowhere/pose"}})
    rig = rig_from_dict(doc)
    bus = MemoryBus()
    frames: list[tuple[str, bytes]] = []
    bus.subscribe(KEYS.edge_frames, lambda k, p: frames.append((k, p)))
    settings = Settings(common=CommonSettings(run_id="t", cameras=3, epoch_s=time.time() - 60,
                                              time_scale=1.0))
    app = create_app(settings, bus=bus, rig=rig)
    robot = Robot(bus)
    with TestClient(app) as client:
        robot.frame()
        wait(lambda: frames, "a first frame")
        for reason, send in bad_samples(robot).items():
            before = len(frames)
            send()
            if reason == "lost":
                wait(lambda: metric(client.get("/metrics").text,
                                    "aoi3d_ingest_frames_lost_total", camera="cam1") == 4,
                     "4 frames lost")
            else:
                wait(lambda r=reason: metric(client.get("/metrics").text,
                                             "aoi3d_messages_rejected_total", reason=r) >= 1,
                     f"a rejection counted as {reason}", timeout_s=5.0)
                robot.frame()  # ... and the next good frame goes through
            wait(lambda b=before: len(frames) > b, f"a good frame after {reason}")
        text = client.get("/metrics").text
        assert metric(text, "aoi3d_ingest_rejected_total", camera="cam1",
                      reason="bad_cdr") == 1
        assert metric(text, "aoi3d_ingest_rejected_total", camera="cam2b", reason="no_pose") >= 1
        assert metric(text, "aoi3d_ingest_frames_total", camera="cam1") == len(frames)
        assert metric(text, "aoi3d_frames_generated_total", camera="1") == len(frames)
        assert metric(text, "aoi3d_ingest_frame_age_seconds_count") == len(frames)
        status = client.get("/status").json()
        cam1 = next(c for c in status["cameras"] if c["name"] == "cam1")
        assert cam1["lost"] == 4 and cam1["published"] == len(frames)
        assert set(cam1["rejected"]) >= {"bad_cdr", "unknown_encoding", "image_mismatch",
                                         "too_large", "stamp_future", "stamp_stale",
                                         "stamp_invalid", "bad_attachment",
                                         "type_hash_mismatch", "sequence_replayed"}
        assert status["source"]["format"] == "rmw_zenoh" and "steps aside" in status["link"]
        assert client.get("/readyz").status_code == 200
    for key, payload in frames:
        assert key == KEYS.edge_frame(1)
        np.testing.assert_array_equal(decode_frame(payload).rgb(), RGB)


def test_readiness_waits_for_the_first_frame() -> None:
    rig = rig_from_dict(rig_doc())
    settings = Settings(common=CommonSettings(run_id="t", cameras=2, epoch_s=time.time() - 60))
    with TestClient(create_app(settings, bus=MemoryBus(), rig=rig)) as client:
        r = client.get("/readyz")
        assert r.status_code == 503 and "no frame" in r.json()["reason"]


def test_the_ros_graph_tells_which_rig_topic_nobody_publishes() -> None:
    """rmw_zenoh's liveliness tokens on the bus: a robot node whose cam1 image goes out as
    CompressedImage (the rig says Image) and whose camera info is right. /readyz says which
    image topics have no publisher of the rig's type, /status lists the graph, Prometheus
    counts publishers per topic, and a robot that leaves takes its publishers along."""
    rig = rig_from_dict(rig_doc())
    bus = MemoryBus()
    settings = Settings(common=CommonSettings(run_id="t", cameras=2, epoch_s=time.time() - 60))

    def token(entity_id: int, topic: str, ros_type: str) -> str:
        return ros.liveliness_key(0, "r1", 0, entity_id, "publisher", "robot", topic=topic,
                                  ros_type=ros_type)

    held = [bus.declare_token(ros.liveliness_key(0, "r1", 0, 0, "node", "robot")),
            bus.declare_token(token(1, "/cam1/image_raw", ros.COMPRESSED))]
    with TestClient(create_app(settings, bus=bus, rig=rig)) as client:
        held.append(bus.declare_token(token(2, "/cam1/camera_info", ros.CAMERA_INFO)))
        reason = client.get("/readyz").json()["reason"]
        assert ("no publisher of the rig's type in the ROS graph on /truth/image_raw, "
                "/cam1/image_raw (published as sensor_msgs/msg/CompressedImage)") in reason
        graph = client.get("/status").json()["source"]["graph"]
        assert (graph["nodes"], graph["publishers"]) == (1, 2)
        text = client.get("/metrics").text
        assert metric(text, "aoi3d_ingest_ros_publishers", topic="/cam1/camera_info") == 1
        assert metric(text, "aoi3d_ingest_ros_publishers", topic="/cam1/image_raw") == 0
        for t in held:
            t.undeclare()
        graph = client.get("/status").json()["source"]["graph"]
        assert (graph["nodes"], graph["publishers"]) == (0, 0)
        assert "ROS graph" not in client.get("/readyz").json()["reason"]
