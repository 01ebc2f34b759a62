"""The ROS 2 decoder fuzzed (issue 31): random bytes, random attachments, and mutated real
samples of every type the ingest reads (raw and compressed images, CameraInfo, PoseStamped,
Odometry) never raise anything but ``Rejected`` and never take long — a bad robot cannot crash
or stall the ingest. Valid samples still make frames after any amount of garbage."""

from __future__ import annotations

import contextlib
import time

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from aoi3d.rigfile import rig_from_dict
from services import ros
from services.ingest.core import IngestCore
from services.kit.keys import Keys
from services.kit.rejected import Rejected
from tests.support.fuzz import fuzz
from tests.support.ingest import C2W, EPOCH, GID, OPTICAL, T0, H, W, rig_doc

SETTINGS = fuzz(250)  # tests/support/fuzz.py: `make fuzz` runs it deeper
SLOW_S = 1.0
"""No sample may take longer than this to accept or refuse."""
RGB = np.random.default_rng(1).integers(0, 255, (H, W, 3), dtype=np.uint8)
SAMPLES = {
    ("image", "/cam1/image_raw"): ros.encode_cdr(ros.image_msg(T0, "c", RGB), ros.IMAGE),
    ("image", "/cam2/image_raw/compressed"): ros.encode_cdr(
        ros.compressed_msg(T0, "c", RGB, "jpeg"), ros.COMPRESSED),
    ("camera_info", "/cam1/camera_info"): ros.encode_cdr(
        ros.camera_info_msg(T0, "c", 20.0, 20.0, W / 2, H / 2, W, H), ros.CAMERA_INFO),
    ("pose", "/cam1/pose"): ros.encode_cdr(ros.pose_stamped_msg(T0, "w", C2W @ OPTICAL),
                                           ros.POSE_STAMPED),
}
PNG = ros.encode_cdr(ros.compressed_msg(T0, "c", RGB, "png"), ros.COMPRESSED)
ODOM = ros.encode_cdr(ros.odometry_msg(T0, "w", "c", C2W @ OPTICAL), ros.ODOMETRY)


def _core() -> IngestCore:
    doc = rig_doc()
    doc["cameras"].append({"name": "cam3", "image": "/cam3/image_raw", "intrinsics":
                           doc["cameras"][0]["intrinsics"],
                           "pose": {"topic": "/cam3/odom", "type": "Odometry"}})
    return IngestCore(rig_from_dict(doc), Keys("t"), epoch_s=EPOCH, time_scale=1.0)


CORE = _core()
ROUTES = {(r.kind, r.topic): r for r in CORE.routes}
SEQ = iter(range(1, 10**9))


def _feed(kind: str, topic: str, payload: bytes, attachment: bytes | None = None) -> None:
    route = ROUTES[(kind, topic)]
    key = CORE.format.key(topic, route.ros_type)
    if attachment is None:
        attachment = ros.build_attachment(next(SEQ), int(T0 * 1e9), GID)
    t = time.perf_counter()
    try:
        out = CORE.on_sample(route, key, payload, attachment, T0 + 0.01)
        for frame in out:
            assert frame.payload
    except Rejected as err:
        assert err.reason and " " not in err.reason
    CORE.expire(T0 + 10.0)
    took = time.perf_counter() - t
    assert took < SLOW_S, f"{kind} {topic}: {took:.2f} s"


@SETTINGS
@given(st.sampled_from([*sorted(SAMPLES), ("pose", "/cam3/odom")]), st.binary(max_size=4096))
def test_random_payloads_are_accepted_or_rejected(which, payload: bytes) -> None:
    _feed(*which, payload)
    _feed(*which, ros.CDR_LE + payload)  # past the CDR header


@SETTINGS
@given(st.binary(max_size=64))
def test_random_attachments_are_accepted_or_rejected(attachment: bytes) -> None:
    _feed("image", "/cam1/image_raw", SAMPLES[("image", "/cam1/image_raw")], attachment)
    try:
        ros.parse_attachment(attachment)
    except Rejected as err:
        assert err.reason == "bad_attachment"


_TOKEN = ros.liveliness_key(0, "s1", 0, 1, "publisher", "robot", topic="/cam1/image_raw",
                            ros_type=ros.IMAGE)


@SETTINGS
@given(st.one_of(st.text(max_size=200),
                 st.lists(st.sampled_from([*_TOKEN.split("/"), "", "%", "NN", "MP", "9"]),
                          max_size=16).map("/".join)))
def test_any_liveliness_token_is_read_or_counted(key: str) -> None:
    """A token of the ROS graph in any layout (random text, and the parts of a real one in
    any order): a GraphEntity or ValueError from the parser, and the core counts what it
    cannot read and goes on."""
    with contextlib.suppress(ValueError):
        ros.parse_liveliness(key)
    before = CORE.ros_graph.unparsed
    CORE.on_liveliness(key, True)
    assert key in CORE.ros_graph.entities or CORE.ros_graph.unparsed == before + 1
    CORE.topic_publishers()
    CORE.on_liveliness(key, False)
    assert key not in CORE.ros_graph.entities


@SETTINGS
@given(st.sampled_from([*sorted(SAMPLES), "png", "odom"]), st.data())
def test_mutated_real_samples_are_accepted_or_rejected(which, data) -> None:
    """Byte changes and truncations of real samples: lengths, strings, sizes and pixels."""
    if which == "png":
        which, good = ("image", "/cam2/image_raw/compressed"), PNG
    elif which == "odom":
        which, good = ("pose", "/cam3/odom"), ODOM
    else:
        good = SAMPLES[which]
    raw = bytearray(good)
    for _ in range(data.draw(st.integers(1, 8))):
        # the first 64 bytes hold the header and the sizes: hit them often
        hi = data.draw(st.sampled_from([min(64, len(raw)), len(raw)]))
        raw[data.draw(st.integers(0, hi - 1))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    _feed(*which, bytes(raw[:cut] if data.draw(st.booleans()) else raw))


def test_good_samples_still_make_frames_after_the_garbage() -> None:
    core = _core()
    routes = {(r.kind, r.topic): r for r in core.routes}
    rng = np.random.default_rng(7)
    for i in range(200):
        which = list(SAMPLES)[i % len(SAMPLES)]
        bad = rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
        route = routes[which]
        with contextlib.suppress(Rejected):
            core.on_sample(route, core.format.key(which[1], route.ros_type), bad,
                           ros.build_attachment(i + 1, int(T0 * 1e9), GID), T0)
    seq = 10_000
    out = []
    for which in [("camera_info", "/cam1/camera_info"), ("pose", "/cam1/pose"),
                  ("image", "/cam1/image_raw")]:
        seq += 1
        route = routes[which]
        out += core.on_sample(route, core.format.key(which[1], route.ros_type), SAMPLES[which],
                              ros.build_attachment(seq, int(T0 * 1e9), GID), T0 + 0.01)
    assert [f.camera_id for f in out] == [1]
