"""The service kit: key matching, buses, hand-off queue, codec validation, settings, proto."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from aoi3d.scene.camera import Camera
from services.kit import codec
from services.kit.bus import Inbox
from services.kit.keys import Keys
from services.kit.membus import MemoryBus, key_matches
from services.kit.observe import Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import RejectReason
from services.kit.settings import CommonSettings

ROOT = Path(__file__).resolve().parents[2]


def _camera(w: int = 8, h: int = 6) -> Camera:
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, -4.0, 1.0]
    return Camera(c2w=c2w, fx=10.0, fy=10.0, cx=w / 2, cy=h / 2, width=w, height=h)


def _frame_bytes(camera_id: int = 3, w: int = 8, h: int = 6, **over) -> bytes:
    image = codec.encode_png(np.full((h, w, 3), 128, np.uint8))
    kw = dict(camera_id=camera_id, sequence=7, generation_ms=210.0, scene_time_ms=210.0,
              camera=_camera(w, h), image=image)
    kw.update(over)
    return codec.encode_frame(**kw)


@pytest.mark.parametrize(("pattern", "key", "ok"), [
    ("aoi3d/r/cam/*/frame", "aoi3d/r/cam/3/frame", True),
    ("aoi3d/r/cam/*/frame", "aoi3d/r/cam/3/x/frame", False),
    ("aoi3d/r/**", "aoi3d/r/cam/3/frame", True),
    ("aoi3d/r/**/frame", "aoi3d/r/truth/frame", True),
    ("aoi3d/r/decision", "aoi3d/s/decision", False),
])
def test_key_matches(pattern: str, key: str, ok: bool) -> None:
    assert key_matches(pattern, key) is ok


def test_keys_and_memory_bus() -> None:
    keys, bus, got = Keys("run1"), MemoryBus(), []
    bus.subscribe(keys.edge_frames, lambda k, p: got.append((k, p)))
    bus.publish(keys.edge_frame(4), b"x")
    bus.publish(keys.cam_frame(4), b"y")
    assert got == [("aoi3d/run1/site1/edge/4/frame", b"x")]
    assert bus.messages(keys.cam_frames) == [b"y"]


def test_inbox_drops_oldest_and_times_out() -> None:
    reported = []
    box = Inbox(maxsize=2, on_drop=lambda: reported.append(1))
    for i in range(3):
        box.put(i)
    assert box.dropped == 1 and len(reported) == 1
    assert box.get(0.01) == 1 and box.get(0.01) == 2
    assert box.get(0.01) is None
    threading.Timer(0.05, box.put, args=("late",)).start()
    assert box.get(2.0) == "late"


def test_frame_round_trip() -> None:
    frame = codec.decode_frame(_frame_bytes(), camera_ids={3})
    assert (frame.camera_id, frame.sequence, frame.generation_ms) == (3, 7, 210.0)
    assert np.allclose(frame.camera.c2w, _camera().c2w)
    assert frame.rgb().shape == (6, 8, 3)
    stamped = codec.decode_frame(codec.with_delivery(_frame_bytes(), 275.0))
    assert stamped.delivery_ms == 275.0


def _expect(reason: str, payload: bytes, **kw) -> None:
    with pytest.raises(Rejected) as err:
        codec.decode_frame(payload, **kw)
    assert err.value.reason == reason, err.value


def test_frame_validation_rejects_bad_input() -> None:
    good = _frame_bytes()
    _expect("malformed", good[: len(good) // 2])
    _expect("malformed", b"\xff\xff\xff garbage")
    _expect("unknown_camera", good, camera_ids={1, 2})
    msg = pb.Frame.FromString(good)
    msg.pose.c2w[0] = math.nan
    _expect("bad_pose", msg.SerializeToString())
    msg = pb.Frame.FromString(good)
    msg.pose.c2w[0] = 2.0  # scaled axis: not a rotation
    _expect("bad_pose", msg.SerializeToString())
    msg = pb.Frame.FromString(good)
    msg.intrinsics.width = 16  # image stays 8 wide
    _expect("image_size_mismatch", msg.SerializeToString())
    msg = pb.Frame.FromString(good)
    msg.image.data = msg.image.data[:30]
    with pytest.raises(Rejected):
        codec.decode_frame(msg.SerializeToString()).rgb()
    msg = pb.Frame.FromString(good)
    msg.generation_ms = math.inf
    _expect("non_finite", msg.SerializeToString())


def test_rejections_count_by_reason() -> None:
    from prometheus_client import CollectorRegistry, generate_latest

    reg = CollectorRegistry()
    rej = Rejections(reg, log_interval_s=60)
    for _ in range(3):
        rej.reject(Rejected(RejectReason.MALFORMED, "x"), "k")
    assert rej.total("malformed") == 3
    text = generate_latest(reg).decode()
    assert 'aoi3d_messages_rejected_total{reason="malformed"} 3.0' in text


def test_settings_from_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AOI3D_ZENOH_CONNECT", "tcp/10.0.0.1:7447, tcp/127.0.0.1:7448")
    monkeypatch.setenv("AOI3D_TIME_SCALE", "0.5")
    s = CommonSettings()
    assert s.zenoh_connect == ["tcp/10.0.0.1:7447", "tcp/127.0.0.1:7448"]
    assert s.time_scale == 0.5
    monkeypatch.setenv("AOI3D_TIME_SCALE", "-1")
    with pytest.raises(ValueError, match="time_scale"):
        CommonSettings()


def test_generated_protobuf_is_current(tmp_path: Path) -> None:
    """`make proto` output must match what is committed (fails when proto/ changed alone)."""
    pytest.importorskip("grpc_tools")
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{ROOT / 'proto'}",
                    f"--python_out={tmp_path}", f"--pyi_out={tmp_path}",
                    str(ROOT / "proto" / "aoi3d.proto")], check=True)
    for name in ("aoi3d_pb2.py", "aoi3d_pb2.pyi"):
        fresh = (tmp_path / name).read_text()
        committed = (ROOT / "services" / "kit" / "pb" / name).read_text()
        assert fresh == committed, f"{name} is stale: run `make proto`"
