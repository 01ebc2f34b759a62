"""The ingest core (issue 31): ROS 2 samples in, the pipeline's Frames out — every bad input a
rejection with its reason, the clock offset measured and applied, sequence gaps counted as
losses, poses matched by stamp. Pure: no bus, no threads."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from aoi3d.rigfile import rig_from_dict
from aoi3d.scene import look_at
from services import ros
from services.ingest.core import HOLD_S, IngestCore
from services.kit.codec import decode_frame
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected
from tests.support.fakeclock import FakeClock
from tests.support.ingest import C2W, EPOCH, GID, INTR, OPTICAL, T0, H, W, rig_doc


def make_core(**over) -> IngestCore:
    through = over.pop("through_network", False)
    return IngestCore(rig_from_dict(rig_doc(**over)), Keys("t"), epoch_s=EPOCH, time_scale=1.0,
                      through_network=through)


def route(core: IngestCore, kind: str, topic: str):
    return next(r for r in core.routes if r.kind == kind and r.topic == topic)


RGB = np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8)


class Feed:
    """Sends samples of one core as an rmw_zenoh robot would (sequence numbers per topic)."""

    def __init__(self, core: IngestCore, hash_: str | None = None) -> None:
        self.core = core
        self.seq: dict[str, int] = {}
        self.hash = hash_

    def send(self, kind: str, topic: str, msg, receipt: float, *, seq: int | None = None,
             payload: bytes | None = None, attachment: bytes | None = b"",
             key: str | None = None, source_ns: int | None = None):
        r = route(self.core, kind, topic)
        n = self.seq.get(topic, 0) + 1 if seq is None else seq
        self.seq[topic] = n
        if attachment == b"":
            ns = int(msg.header.stamp.sec * 1e9 + msg.header.stamp.nanosec) \
                if source_ns is None else source_ns
            attachment = ros.build_attachment(n, ns, GID)
        data = ros.encode_cdr(msg, r.ros_type) if payload is None else payload
        return self.core.on_sample(r, key or self.core.format.key(topic, r.ros_type, self.hash),
                                   data, attachment, receipt)

    def pose(self, stamp: float, receipt: float, m: np.ndarray = C2W):
        return self.send("pose", "/cam1/pose", ros.pose_stamped_msg(stamp, "w", m @ OPTICAL),
                         receipt)

    def info(self, stamp: float, receipt: float, w: int = W, h: int = H):
        return self.send("camera_info", "/cam1/camera_info",
                         ros.camera_info_msg(stamp, "c", 20.0, 20.0, w / 2, h / 2, w, h), receipt)

    def image(self, stamp: float, receipt: float, topic: str = "/cam1/image_raw", rgb=RGB,
              **kw):
        msg = (ros.compressed_msg(stamp, "c", rgb, "jpeg") if topic.endswith("compressed")
               else ros.image_msg(stamp, "c", rgb))
        return self.send("image", topic, msg, receipt, **kw)


def ready(core: IngestCore, stamp: float = T0, receipt: float | None = None) -> Feed:
    feed = Feed(core)
    feed.info(stamp, stamp if receipt is None else receipt)
    feed.pose(stamp, stamp if receipt is None else receipt)
    return feed


def rejected(fn, reason: str) -> Rejected:
    with pytest.raises(Rejected) as info:
        fn()
    assert info.value.reason == reason, info.value
    return info.value


# ---------------------------------------------------------------- the good path
def test_a_posed_image_becomes_a_frame_on_the_edge_key_delivered_at_receipt() -> None:
    core = make_core()
    feed = ready(core)
    (out,) = feed.image(T0, T0 + 0.02)
    assert out.key == Keys("t").edge_frame(1)
    frame = decode_frame(out.payload)
    assert frame.camera_id == 1 and frame.sequence == 1
    assert frame.generation_ms == pytest.approx(100_000.0, abs=1e-3)  # stamp on the sim clock
    assert frame.delivery_ms == pytest.approx(100_020.0, abs=1e-3)    # receipt
    assert frame.send_ms == frame.delivery_ms
    np.testing.assert_allclose(frame.camera.c2w, C2W, atol=1e-9)     # its own pose, not a rig's
    np.testing.assert_array_equal(frame.rgb(), RGB)
    assert out.age_s == pytest.approx(0.02)


def test_the_truth_camera_publishes_on_the_truth_key_and_emulated_delay_goes_via_cam_keys() -> None:
    core = make_core(through_network=True)
    feed = ready(core)
    (truth,) = feed.image(T0, T0 + 0.01, topic="/truth/image_raw")
    assert truth.key == Keys("t").truth and decode_frame(truth.payload).camera_id == 0
    (cam,) = feed.image(T0, T0 + 0.01)
    frame = decode_frame(cam.payload)
    assert cam.key == Keys("t").cam_frame(1) and frame.delivery_ms == 0.0
    assert frame.send_ms == pytest.approx(100_010.0, abs=1e-3)  # the network delays from here


def test_each_frame_carries_the_pose_matched_to_its_stamp() -> None:
    core = make_core()
    feed = ready(core)
    moved = look_at((1.0, -4.0, 1.0), (0.0, 0.0, 0.5))
    feed.pose(T0 + 1.0, T0 + 1.0, moved)
    (a,) = feed.image(T0 + 0.03, T0 + 1.01)  # nearest: the first pose (0.03 s away)
    (b,) = feed.image(T0 + 0.98, T0 + 1.02)  # nearest: the moved one (0.02 s away)
    np.testing.assert_allclose(decode_frame(a.payload).camera.c2w, C2W, atol=1e-9)
    np.testing.assert_allclose(decode_frame(b.payload).camera.c2w, moved, atol=1e-9)
    rejected(lambda: feed.image(T0 + 0.5, T0 + 1.03), "no_pose")  # 0.47 s from either


def test_frames_are_resized_to_the_working_size_with_their_intrinsics() -> None:
    core = make_core(size=[12, 9])
    feed = ready(core)
    (out,) = feed.image(T0, T0)
    frame = decode_frame(out.payload)
    assert (frame.camera.width, frame.camera.height) == (12, 9)
    assert frame.camera.fx == pytest.approx(10.0) and frame.camera.cx == pytest.approx(6.0)
    assert frame.rgb().shape == (9, 12, 3)


def test_compressed_jpeg_and_png_decode() -> None:
    core = make_core()
    feed = Feed(core)
    smooth = np.dstack([*np.meshgrid(np.linspace(0, 255, W), np.linspace(0, 255, H)),
                        np.full((H, W), 90.0)]).astype(np.uint8)
    (out,) = feed.image(T0, T0, topic="/cam2/image_raw/compressed", rgb=smooth)
    err = float(np.abs(decode_frame(out.payload).rgb().astype(int) - smooth).mean())
    assert err < 8, err  # jpeg: lossy
    png = ros.compressed_msg(T0 + 0.1, "c", RGB, "png")
    (out,) = feed.send("image", "/cam2/image_raw/compressed", png, T0 + 0.1)
    np.testing.assert_array_equal(decode_frame(out.payload).rgb(), RGB)


@pytest.mark.parametrize("encoding", ["bgr8", "rgba8", "bgra8", "mono8", "mono16"])
def test_raw_encodings_become_rgb(encoding: str) -> None:
    core = make_core()
    feed = ready(core)
    msg = ros.image_msg(T0, "c", RGB)
    bpp = ros.ENCODINGS[encoding]
    gray = RGB[:, :, 0]
    data = {"bgr8": RGB[:, :, ::-1], "rgba8": np.dstack([RGB, np.full((H, W), 255, np.uint8)]),
            "bgra8": np.dstack([RGB[:, :, ::-1], np.full((H, W), 7, np.uint8)]),
            "mono8": gray, "mono16": (gray.astype("<u2") << 8)}[encoding]
    msg.encoding, msg.step = encoding, W * bpp
    msg.data = np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    (out,) = feed.send("image", "/cam1/image_raw", msg, T0)
    want = RGB if bpp in (3, 4) else np.repeat(gray[:, :, None], 3, axis=2)
    np.testing.assert_array_equal(decode_frame(out.payload).rgb(), want)


def test_the_bridge_format_has_namespaced_keys_and_no_attachment() -> None:
    core = make_core(source={"format": "bridge", "namespace": "robot1"})
    assert {r.key_expr for r in core.routes} >= {"robot1/cam1/image_raw", "robot1/cam1/pose"}
    feed = Feed(core)
    feed.send("camera_info", "/cam1/camera_info",
              ros.camera_info_msg(T0, "c", 20, 20, W / 2, H / 2, W, H), T0, attachment=None)
    feed.send("pose", "/cam1/pose", ros.pose_stamped_msg(T0, "w", C2W @ OPTICAL), T0,
              attachment=None)
    outs = [feed.send("image", "/cam1/image_raw", ros.image_msg(T0 + i, "c", RGB), T0 + i,
                      attachment=None) for i in (0.0, 0.01)]
    assert [decode_frame(o[0].payload).sequence for o in outs] == [1, 2]  # its own count


def test_humble_placeholder_and_jazzy_hash_are_both_accepted() -> None:
    core = make_core()
    for hash_ in (None, ros.HUMBLE_HASH):
        feed = ready(core)
        feed.hash = hash_
        feed.seq = {"/cam1/image_raw": core.cameras["cam1"].last_seq.get(
            ("/cam1/image_raw", GID), 0)}
        assert feed.image(T0 + 0.001, T0 + 0.01)


def test_an_image_that_overtook_its_pose_waits_for_it() -> None:
    core = make_core()
    feed = Feed(core)
    feed.info(T0, T0)
    assert feed.image(T0, T0) == []  # held: its pose may still come
    (out,) = feed.pose(T0, T0 + 0.01)  # ... and it does
    assert decode_frame(out.payload).camera_id == 1
    assert feed.image(T0 + 0.1, T0 + 0.1) == []
    frames, refused = core.expire(T0 + 0.1 + HOLD_S + 0.01)
    assert frames == [] and [(c, e.reason) for c, e in refused] == [("cam1", "no_pose")]
    assert core.cameras["cam1"].rejected["no_pose"] == 1


# ---------------------------------------------------------------- every bad input, a reason
def test_no_intrinsics_is_refused_once_the_wait_is_over() -> None:
    core = make_core()
    feed = Feed(core)
    feed.pose(T0, T0)
    assert feed.image(T0, T0) == []
    _, refused = core.expire(T0 + HOLD_S + 0.01)
    assert [e.reason for _, e in refused] == ["no_intrinsics"]


def test_unknown_encodings() -> None:
    core = make_core()
    feed = ready(core)
    msg = ros.image_msg(T0, "c", RGB)
    msg.encoding = "yuv422"
    rejected(lambda: feed.send("image", "/cam1/image_raw", msg, T0), "unknown_encoding")
    cmsg = ros.compressed_msg(T0, "c", RGB, "png")
    cmsg.format = "tiff"
    rejected(lambda: feed.send("image", "/cam2/image_raw/compressed", cmsg, T0),
             "unknown_encoding")


def test_truncated_and_garbled_cdr() -> None:
    core = make_core()
    feed = ready(core)
    good = ros.encode_cdr(ros.image_msg(T0, "c", RGB), ros.IMAGE)
    for bad in (good[:len(good) // 2], good[:6], b"", b"\x00\x00\x00\x00" + good[4:],
                good + b"\x00" * 64, good[:4] + b"\xff" * 12 + good[16:]):
        rejected(lambda b=bad: feed.image(T0, T0, payload=b), "bad_cdr")
    assert core.cameras["cam1"].rejected["bad_cdr"] == 6


@pytest.mark.parametrize("field,value", [("step", W * 3 - 1), ("height", H + 1),
                                         ("width", W + 1), ("data", b"\x00" * 10)])
def test_width_height_step_and_data_that_disagree(field: str, value) -> None:
    core = make_core()
    feed = ready(core)
    msg = ros.image_msg(T0, "c", RGB)
    setattr(msg, field, np.frombuffer(value, np.uint8) if field == "data" else value)
    rejected(lambda: feed.send("image", "/cam1/image_raw", msg, T0), "image_mismatch")


def test_an_image_of_another_size_than_its_camera_info() -> None:
    core = make_core()
    feed = Feed(core)
    feed.info(T0, T0, w=W * 2, h=H * 2)
    feed.pose(T0, T0)
    err = rejected(lambda: feed.image(T0, T0), "image_mismatch")
    assert "intrinsics" in err.detail


def test_an_image_over_the_size_limit_is_refused_before_decoding(monkeypatch) -> None:
    core = make_core(max_image_bytes=1024)
    feed = ready(core)

    def boom(*_a, **_k):
        raise AssertionError("decoded an oversized sample")

    monkeypatch.setattr(ros.typestore(), "deserialize_cdr", boom)
    rejected(lambda: feed.image(T0, T0), "too_large")


def test_an_image_over_the_pixel_limit_is_refused_before_its_pixels_are_decoded() -> None:
    core = make_core(max_image_pixels=100)
    feed = ready(core)
    rejected(lambda: feed.image(T0, T0), "too_large")  # raw: declared 24x18
    # a compressed one: only its header is read (a decompression bomb costs nothing)
    from PIL import Image as PILImage

    buf = io.BytesIO()
    PILImage.new("RGB", (4000, 4000)).save(buf, format="PNG")
    msg = ros.compressed_msg(T0, "c", RGB, "png")
    msg.data = np.frombuffer(buf.getvalue(), np.uint8)
    rejected(lambda: feed.send("image", "/cam2/image_raw/compressed", msg, T0), "too_large")


def test_compressed_data_that_is_not_what_its_format_says() -> None:
    core = make_core()
    feed = Feed(core)
    msg = ros.compressed_msg(T0, "c", RGB, "jpeg")
    msg.data = msg.data[: len(msg.data) // 3]
    rejected(lambda: feed.send("image", "/cam2/image_raw/compressed", msg, T0), "bad_image")
    msg = ros.compressed_msg(T0, "c", RGB, "png")
    msg.format = "jpeg"
    rejected(lambda: feed.send("image", "/cam2/image_raw/compressed", msg, T0), "bad_image")


def test_a_camera_with_no_pose() -> None:
    core = make_core()
    feed = Feed(core)
    feed.info(T0, T0)
    feed.pose(T0 + 5.0, T0 + 5.0)  # a pose, but seconds away: none will match
    rejected(lambda: feed.image(T0, T0 + 5.0), "no_pose")


def test_bad_poses_and_intrinsics() -> None:
    core = make_core()
    feed = Feed(core)
    nan = ros.pose_stamped_msg(T0, "w", C2W)
    nan.pose.position.x = math.nan
    rejected(lambda: feed.send("pose", "/cam1/pose", nan, T0), "bad_pose")
    zero = ros.pose_stamped_msg(T0, "w", C2W)
    zero.pose.orientation.x = zero.pose.orientation.y = zero.pose.orientation.z = 0.0
    zero.pose.orientation.w = 0.0
    rejected(lambda: feed.send("pose", "/cam1/pose", zero, T0), "bad_pose")
    info = ros.camera_info_msg(T0, "c", 0.0, 20.0, W / 2, H / 2, W, H)
    rejected(lambda: feed.send("camera_info", "/cam1/camera_info", info, T0), "bad_intrinsics")


def test_stamps_out_of_range() -> None:
    core = make_core(clock={"future_tolerance_s": 0.5, "max_age_s": 30})
    feed = ready(core)
    rejected(lambda: feed.image(0.0, T0), "stamp_invalid")                  # not stamped
    msg = ros.image_msg(T0, "c", RGB)
    msg.header.stamp.nanosec = 1_500_000_000
    rejected(lambda: feed.send("image", "/cam1/image_raw", msg, T0), "stamp_invalid")
    rejected(lambda: feed.image(T0 + 0.6, T0), "stamp_future")              # beyond tolerance
    rejected(lambda: feed.image(T0 - 31.0, T0), "stamp_stale")
    early = Feed(make_core())
    early.info(EPOCH - 1.0, EPOCH - 1.0)
    early.pose(EPOCH - 1.0, EPOCH - 1.0)
    rejected(lambda: early.image(EPOCH - 1.0, EPOCH - 0.9), "stamp_before_run")
    # within the tolerance: clamped to the receipt (AoI is never negative), counted
    feed.pose(T0 + 0.3, T0)
    (out,) = feed.image(T0 + 0.3, T0)
    assert decode_frame(out.payload).generation_ms == pytest.approx(100_000.0, abs=1e-3)
    assert core.cameras["cam1"].clamped == 1


def test_sequence_gaps_count_as_losses_and_replays_are_refused() -> None:
    core = make_core()
    feed = ready(core)
    assert feed.image(T0, T0, seq=1)
    assert feed.image(T0 + 0.01, T0 + 0.01, seq=2)
    assert feed.image(T0 + 0.02, T0 + 0.02, seq=6)  # 3, 4, 5 never came
    assert core.cameras["cam1"].lost == 3
    rejected(lambda: feed.image(T0 + 0.03, T0 + 0.03, seq=6), "sequence_replayed")
    rejected(lambda: feed.image(T0 + 0.04, T0 + 0.04, seq=4), "sequence_replayed")
    # a restarted publisher (a new id) starts its own sequence
    other = ros.build_attachment(1, int(T0 * 1e9), b"\x09" * 16)
    assert feed.image(T0 + 0.04, T0 + 0.04, attachment=other)
    assert core.cameras["cam1"].lost == 3


def test_bad_attachments_and_type_hashes() -> None:
    core = make_core()
    feed = ready(core)
    rejected(lambda: feed.image(T0, T0, attachment=None), "bad_attachment")
    rejected(lambda: feed.image(T0, T0, attachment=b"\x01\x02\x03"), "bad_attachment")
    key = core.format.key("/cam1/image_raw", ros.IMAGE, "RIHS01_" + "0" * 64)
    rejected(lambda: feed.image(T0, T0, key=key), "type_hash_mismatch")


def test_the_older_named_attachment_layout_is_read() -> None:
    raw = (b"\x0fsequence_number" + (7).to_bytes(8, "little", signed=True)
           + b"\x10source_timestamp" + (123).to_bytes(8, "little", signed=True)
           + b"\x0asource_gid" + b"\x10" + GID)
    assert ros.parse_attachment(raw) == ros.Attachment(7, 123, GID)
    assert ros.parse_attachment(ros.build_attachment(7, 123, GID)) == ros.Attachment(7, 123, GID)


# ---------------------------------------------------------------- time: the clock offset
def test_the_clock_offset_is_measured_shown_and_applied_when_auto() -> None:
    ahead = 5.0  # the robot's clock is 5 s ahead of the edge's
    fixed = make_core()
    feed = ready(fixed, T0 + ahead, T0)
    rejected(lambda: feed.image(T0 + ahead, T0 + 0.01), "stamp_future")
    assert fixed.cameras["cam1"].offset_estimate_s == pytest.approx(ahead, abs=1e-6)
    status = fixed.status(T0)["cameras"][1]
    assert status["clock_offset_s"] == pytest.approx(ahead) and status[
        "clock_offset_in_force_s"] == 0.0

    auto = make_core(clock={"offset_s": "auto"})
    feed = ready(auto, T0 + ahead, T0)
    (out,) = feed.image(T0 + ahead + 0.02, T0 + 0.05)
    # generation = stamp − measured offset: 30 ms before its receipt
    assert decode_frame(out.payload).generation_ms == pytest.approx(100_020.0, abs=0.5)

    given = make_core(clock={"offset_s": ahead})
    feed = ready(given, T0 + ahead, T0)
    (out,) = feed.image(T0 + ahead, T0 + 0.04)
    assert decode_frame(out.payload).generation_ms == pytest.approx(100_000.0, abs=1e-3)
    assert out.age_s == pytest.approx(0.04)


def test_the_attachments_source_time_measures_the_offset_and_the_publish_delay() -> None:
    core = make_core()
    feed = ready(core)
    # captured at T0, published 20 ms later by the robot, received 30 ms after that
    (out,) = feed.image(T0, T0 + 0.05, source_ns=int((T0 + 0.02) * 1e9))
    s = core.status(T0 + 0.05)["cameras"][1]
    assert s["publish_delay_ms"] == pytest.approx(20.0, abs=0.01)
    assert out.age_s == pytest.approx(0.05)


def test_time_scale_maps_stamps_to_the_sim_clock() -> None:
    core = IngestCore(rig_from_dict(rig_doc()), Keys("t"), epoch_s=EPOCH, time_scale=0.1)
    feed = ready(core)
    (out,) = feed.image(T0, T0 + 0.1)
    frame = decode_frame(out.payload)
    assert frame.generation_ms == pytest.approx(10_000.0, abs=1e-3)
    assert frame.delivery_ms == pytest.approx(10_010.0, abs=1e-3)


def test_status_says_when_nothing_can_be_scored() -> None:
    doc = rig_doc()
    doc.pop("truth")
    core = IngestCore(rig_from_dict(doc), Keys("t"), epoch_s=EPOCH, time_scale=1.0)
    st = core.status(T0)
    assert st["truth"] is None and "cannot be scored" in st["scoring"]
    assert [c["id"] for c in st["cameras"]] == [1, 2, 3]
    assert isinstance(pb.Frame, type)


# ---------------------------------------------------------------- IP cameras and videos
def url_rig(**over) -> dict:
    doc = rig_doc(**over)
    doc["cameras"].append({"name": "ipcam", "url": "rtsp://127.0.0.1:8554/ipcam",
                           "listen": True, "intrinsics": INTR,
                           "pose": {"c2w": C2W.ravel().tolist()}})
    return doc


def test_a_url_cameras_frames_take_the_same_path() -> None:
    core = IngestCore(rig_from_dict(url_rig()), Keys("t"), epoch_s=EPOCH, time_scale=1.0)
    assert all(r.topic != "rtsp://127.0.0.1:8554/ipcam" for r in core.routes)
    (out,) = core.on_video("ipcam", RGB, T0, T0 + 0.05)
    frame = decode_frame(out.payload)
    assert out.key == Keys("t").edge_frame(3) and frame.camera_id == 3
    assert frame.generation_ms == pytest.approx(100_000.0, abs=1e-3)
    assert frame.sequence == 1 and out.age_s == pytest.approx(0.05)
    rejected(lambda: core.on_video("ipcam", RGB, T0 + 5.0, T0), "stamp_future")
    rejected(lambda: core.on_video("ipcam", RGB, float("nan"), T0), "stamp_invalid")
    rejected(lambda: core.on_video("ipcam", RGB[:, :10], T0, T0), "image_mismatch")
    status = core.status(T0)["cameras"][3]
    assert status["image_type"] == "rtsp" and status["image"].startswith("rtsp://")
    assert status["rejected"] == {"stamp_future": 1, "stamp_invalid": 1, "image_mismatch": 1}


def test_url_cameras_in_the_rig() -> None:
    rig = rig_from_dict(url_rig())
    assert rig.cameras[3].kind == "rtsp" and rig.cameras[3].is_rtsp
    doc = url_rig()
    doc["cameras"][3]["image"] = "/x"
    assert "exactly one of image" in errors_of(doc)
    doc = url_rig()
    doc["cameras"][3]["intrinsics"] = {"camera_info": "/x/info"}
    assert "intrinsics as values" in errors_of(doc)
    doc = url_rig()
    doc["cameras"][3]["url"] = "/videos/cam.mp4"
    assert "listen and stamps are for rtsp" in errors_of(doc)
    doc["cameras"][3]["listen"] = False
    assert rig_from_dict(doc).cameras[3].kind == "video"


def errors_of(doc) -> str:
    from aoi3d.rigfile import RigError

    with pytest.raises(RigError) as info:
        rig_from_dict(doc)
    return str(info.value)


def test_a_video_file_plays_in_a_loop_at_its_rate(tmp_path) -> None:
    import av

    from services.ingest.video import StreamEnded, read_video

    path = tmp_path / "cam.mp4"
    with av.open(str(path), mode="w") as out:
        stream = out.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        for i in range(6):
            frame = av.VideoFrame.from_ndarray(np.full((H, W, 3), 40 * i, np.uint8),
                                               format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    got = []
    with pytest.raises(StreamEnded):
        for f in read_video(str(path), time_scale=10.0):
            got.append(f)
    assert len(got) == 6 and got[0].rgb.shape == (H, W, 3)
    gaps = np.diff([f.stamp_s for f in got])
    np.testing.assert_allclose(gaps, 1 / 30 / 10, atol=1e-6)  # its rate, scaled
    assert all(f.receipt_s >= f.stamp_s - 0.02 for f in got)
    with pytest.raises(ValueError, match="pixels"):
        next(read_video(str(path), max_pixels=10))


# ---------------------------------------------------------------- the test robot
class _StubDataset:
    """Two cameras (0 held out, 1 trains) of a 1 s loop at 10 fps."""

    heldout_id = 0
    train_ids = (1,)
    aabb = np.array([-2, -2, -1, 2, 2, 2.0])

    def __init__(self) -> None:
        from aoi3d.scene import Camera

        self.cameras = [Camera(c2w=C2W, width=W, height=H, **{k: INTR[k] for k in
                                                             ("fx", "fy", "cx", "cy")})] * 2
        self.shown: list[int] = []

    def frame_index(self, time_ms: float) -> int:
        return int(time_ms // 100) % 10

    def frame(self, camera_id: int, index: int) -> np.ndarray:
        self.shown.append(index)
        return RGB


@pytest.mark.parametrize("fmt", ["rmw_zenoh", "bridge"])
def test_the_robot_phase_locks_to_the_pipelines_clock_and_its_samples_decode(fmt) -> None:
    from services.ros.robot import PublishConfig, Robot, rig_document

    ds = _StubDataset()
    cfg = PublishConfig(dataset=None, format=fmt, namespace="r" if fmt == "bridge" else "",
                        period_ms=30.0, time_scale=0.5, frames=2, epoch_s=EPOCH)
    sent = []
    now = EPOCH + 0.13  # 130 ms wall = 65 sim ms into the run: the next grid frame is k = 3
    robot = Robot(cfg, lambda k, p, a: sent.append((k, p, a)), dataset=ds, clock=lambda: now)
    robot.run()
    core = IngestCore(rig_from_dict(rig_document(cfg, ds)), Keys("t"), epoch_s=EPOCH,
                      time_scale=0.5)
    routes = [(r, r.key_expr) for r in core.routes]
    from services.kit.membus import key_matches

    frames = []
    for key, payload, att in sent:  # (the truth camera's pose and info: no subscriber)
        for route in [r for r, expr in routes if key_matches(expr, key)]:
            frames += core.on_sample(route, key, payload, att, now + 0.2)
    gens = sorted(decode_frame(f.payload).generation_ms for f in frames)
    # k·C on the sim clock, exactly: a stamp maps to its 1 ms slot, so the truth frame of a
    # decision's time pairs with it (float noise of the epoch would make it 'after t')
    assert gens == [90.0, 90.0, 120.0, 120.0]
    assert ds.shown == [0, 0, 1, 1]  # scene time k·C: frames of 90 and 120 ms
    assert all((a is None) == (fmt == "bridge") for _, _, a in sent)


def test_the_robot_encodes_a_frame_before_its_time_and_sends_its_cameras_together() -> None:
    """Encoding is the robot's cost, not the link's: a frame is encoded before it is due and all
    its cameras go out at its time (encoding them one after another at the due time made the
    last of 19 cameras reach the edge ~60 ms wall after its stamp)."""
    from services import ros
    from services.ros.robot import PublishConfig, Robot

    clock = FakeClock(EPOCH + 0.13)

    class _Slow(_StubDataset):
        def frame(self, camera_id: int, index: int) -> np.ndarray:
            clock.advance(0.01)  # reading and encoding a camera's frame takes 10 ms
            return super().frame(camera_id, index)

    cfg = PublishConfig(dataset=None, period_ms=30.0, time_scale=0.5, frames=2, epoch_s=EPOCH,
                        pose="file", intrinsics="file")
    sent = []
    robot = Robot(cfg, lambda k, p, a: sent.append((k, p, a)), dataset=_Slow(), clock=clock)
    robot.run(clock)
    sources = [ros.parse_attachment(a).source_ns / 1e9 - EPOCH for _, _, a in sent]
    # frames k = 3 and 4 are due at 180 and 240 ms wall: both cameras at exactly that moment
    np.testing.assert_allclose(sources, [0.18, 0.18, 0.24, 0.24], atol=1e-6)
    assert robot.frames_sent == 4 and robot.periods == 2 and robot.skipped == 0


def test_a_robot_behind_skips_to_the_newest_frame_and_encodes_each_frame_once() -> None:
    """Encoding a frame takes longer than a period here (2 cameras × 100 ms against 62.5 ms): the
    robot skips to the newest frame due before it encodes, so no frame is encoded and then
    thrown away, and it counts the periods it skipped."""
    from services.ros.robot import PublishConfig, Robot

    clock = FakeClock(EPOCH)

    class _Slow(_StubDataset):
        def frame(self, camera_id: int, index: int) -> np.ndarray:
            clock.advance(0.1)
            return super().frame(camera_id, index)

    ds = _Slow()
    cfg = PublishConfig(dataset=None, period_ms=25.0, time_scale=0.4, frames=4, epoch_s=EPOCH,
                        pose="file", intrinsics="file")
    robot = Robot(cfg, lambda *_: None, dataset=ds, clock=clock)
    robot.run(clock)
    assert robot.periods == 4 and robot.frames_sent == 8
    assert len(ds.shown) == 8  # every camera's frame encoded once per period sent
    # frames 0, 3, 6, 9: after each 200 ms of encoding the newest due is 3 periods on
    assert robot.skipped == 6 and ds.shown == [0, 0, 0, 0, 1, 1, 2, 2]  # 0, 75, 150, 225 ms


# ---------------------------------------------------------------- the ROS graph
def test_liveliness_tokens_in_rmw_zenohs_layout_read_back() -> None:
    """The layout of rmw_zenoh's liveliness_utils.cpp (Jazzy, and its Humble backport): the
    session, node and entity ids, NN/MP, the enclave, namespace and topic with % for /."""
    key = ros.liveliness_key(7, "a1b2", 0, 3, "publisher", "robot", namespace="/team",
                             topic="/cam1/image_raw", ros_type=ros.COMPRESSED,
                             hash_=ros.HUMBLE_HASH)
    assert key == ("@ros2_lv/7/a1b2/0/3/MP/%/%team/robot/%cam1%image_raw/"
                   "sensor_msgs::msg::dds_::CompressedImage_/TypeHashNotSupported/::,:,:,:,,")
    e = ros.parse_liveliness(key)
    assert (e.kind, e.domain_id, e.session, e.node, e.namespace) == ("publisher", 7, "a1b2",
                                                                     "robot", "/team")
    assert (e.topic, e.ros_type, e.type_hash) == ("/cam1/image_raw", ros.COMPRESSED,
                                                  ros.HUMBLE_HASH)
    node = ros.parse_liveliness(ros.liveliness_key(0, "a1b2", 0, 0, "node", "robot"))
    assert (node.kind, node.topic, node.namespace) == ("node", None, "/")
    jazzy = ros.liveliness_key(0, "z", 0, 1, "publisher", "n", topic="t", ros_type=ros.IMAGE)
    assert ros.parse_liveliness(jazzy).type_hash == ros.type_hash(ros.IMAGE)


@pytest.mark.parametrize("key", [
    "aoi3d/run/pool/worker/1",                                  # another key space
    "@ros2_lv/0/abc/MP/_/talker/%chatter/std_msgs::msg::dds_::String_/1:2:1,10",  # pre-2024
    "@ros2_lv/0/abc/0/0/XX/%/%/node",                           # no entity kind
    "@ros2_lv/0/abc/0/1/MP/%/%/node/%topic",                    # a publisher cut short
    "@ros2_lv/x/abc/0/0/NN/%/%/node",                           # no domain id
])
def test_a_token_in_another_layout_is_a_clear_error(key: str) -> None:
    with pytest.raises(ValueError):
        ros.parse_liveliness(key)


def test_the_graph_shows_who_publishes_each_topic_and_of_what_type() -> None:
    """The rig's cam1 image topic has a publisher of CompressedImage (the rig says Image):
    /status shows it and the hint names it; its camera info has one of the right type; a
    token of another layout is counted; a vanished token leaves the graph."""
    core = make_core()
    assert core.graph_key == "@ros2_lv/0/**" and core.graph_hint() == ""

    def token(entity_id: int, topic: str, ros_type: str) -> str:
        return ros.liveliness_key(0, "s1", 0, entity_id, "publisher", "robot", topic=topic,
                                  ros_type=ros_type)

    wrong = token(1, "/cam1/image_raw", ros.COMPRESSED)
    info = token(2, "/cam1/camera_info", ros.CAMERA_INFO)
    for key in (ros.liveliness_key(0, "s1", 0, 0, "node", "robot"), wrong, info,
                "@ros2_lv/0/abc/MP/_/talker/%chatter/std_msgs::msg::dds_::String_/1:2:1,10"):
        core.on_liveliness(key, True)
    topics = {t["topic"]: t for t in core.topic_publishers()}
    assert topics["/cam1/image_raw"]["publishers"] == 0
    assert topics["/cam1/image_raw"]["other_types"] == [ros.COMPRESSED]
    assert topics["/cam1/camera_info"]["publishers"] == 1
    assert topics["/cam1/camera_info"]["nodes"] == ["/robot"]
    graph = core.status(T0)["source"]["graph"]
    assert (graph["nodes"], graph["publishers"], graph["unparsed_tokens"]) == (1, 2, 1)
    hint = core.graph_hint()
    assert "/cam1/image_raw (published as sensor_msgs/msg/CompressedImage)" in hint
    assert "/truth/image_raw" in hint and "camera_info" not in hint
    core.on_liveliness(info, False)
    assert {t["topic"]: t for t in core.topic_publishers()}["/cam1/camera_info"][
        "publishers"] == 0


def test_a_flood_of_tokens_is_counted_not_kept(monkeypatch) -> None:
    import services.ingest.graph as graph_module

    monkeypatch.setattr(graph_module, "GRAPH_MAX", 3)
    core = make_core()
    keys = [ros.liveliness_key(0, f"s{i}", 0, 0, "node", "n") for i in range(5)]
    for key in keys:
        core.on_liveliness(key, True)
    core.on_liveliness(keys[0], True)  # one already kept: still kept
    assert list(core.ros_graph.entities) == keys[:3] and core.ros_graph.dropped == 2
    assert core.status(T0)["source"]["graph"]["dropped_tokens"] == 2


def test_the_bridge_has_no_graph() -> None:
    core = make_core(source={"format": "bridge", "namespace": "r"})
    assert core.graph_key is None and core.status(T0)["source"]["graph"] is None
