"""The network service: D/G/1/0 links between the camera rig and the edge, on a fast clock."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from aoi3d.channel import Link, camera_rngs
from aoi3d.clock import SimClock
from aoi3d.scene import Camera, look_at
from services.kit.codec import camera_to_pb, decode_frame, encode_frame, encode_png
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.network.app import create_app
from services.network.settings import Settings
from tests.support.metrics import metric
from tests.support.network import CAMERA, IMAGE, W, frame
from tests.support.timeouts import timeout_scale
from tests.support.waits import settle

N_CAMERAS = 3
KEYS = Keys("t")




SCALE = timeout_scale()




def make_app(bus: MemoryBus, clock: SimClock, files_roots: list[str] | None = None,
             **overrides):
    common = CommonSettings(run_id="t", cameras=N_CAMERAS,
                            **({"files_roots": files_roots} if files_roots else {}))
    settings = Settings(common=common,
                        **{"delay": "const:40", **overrides})
    return create_app(settings, bus=bus, clock=clock)




class Arrivals:
    """Records delivered frames with their wall arrival time."""

    def __init__(self, bus: MemoryBus) -> None:
        self.items: list[tuple[float, str, pb.Frame]] = []
        self._cond = threading.Condition()
        bus.subscribe(KEYS.edge_frames, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        msg = pb.Frame()
        msg.ParseFromString(payload)
        with self._cond:
            self.items.append((time.time(), key, msg))
            self._cond.notify_all()

    def wait(self, n: int, timeout_s: float = 3.0) -> list[tuple[float, str, pb.Frame]]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.items) >= n, timeout_s * SCALE), (
                f"{len(self.items)} of {n} frames delivered")
            return list(self.items)


def test_const_delay_delivers_at_the_slot_and_drops_while_busy() -> None:
    clock = SimClock(epoch_s=time.time(), time_scale=1.0)  # 1 sim ms = 1 wall ms
    bus = MemoryBus()
    arrivals = Arrivals(bus)
    with TestClient(make_app(bus, clock)) as client:
        g = float(math.ceil(clock.now_ms()) + 5)
        bus.publish(KEYS.cam_frame(1), frame(1, g, sequence=1))
        bus.publish(KEYS.cam_frame(1), frame(1, g + 10, sequence=2))  # in flight → dropped
        bus.publish(KEYS.cam_frame(1), frame(1, g + 40, sequence=3))  # at the slot → accepted
        got = arrivals.wait(2)
        time.sleep(0.05)
        assert len(arrivals.items) == 2
        for (wall_s, key, msg), seq, slot in zip(got, (1, 3), (g + 40, g + 80), strict=True):
            assert key == KEYS.edge_frame(1)
            assert msg.sequence == seq and msg.delivery_ms == slot
            assert msg.generation_ms == slot - 40
            assert wall_s >= clock.wall_s(slot) - 2e-3, "delivered before its slot"
            assert wall_s < clock.wall_s(slot) + 0.25, "delivered far too late"
            decode_frame(bus.messages(KEYS.edge_frame(1))[0], {1})  # still a valid frame
        text = client.get("/metrics").text
        assert metric(text, "aoi3d_frames_offered_total", camera="1") == 3
        assert metric(text, "aoi3d_frames_dropped_total", camera="1") == 1
        assert metric(text, "aoi3d_frames_delivered_total", camera="1") == 2
        assert metric(text, "aoi3d_link_delay_seconds_count") == 2
        assert metric(text, "aoi3d_link_delay_seconds_sum") == pytest.approx(0.08)
        links = client.get("/channel").json()["links"]
        assert links[0] == {"camera": 1, "delay": "const:40", "mean_delay_ms": 40.0,
                            "offered": 3, "dropped": 1, "delivered": 2, "in_flight": False}
        assert client.get("/readyz").status_code == 200


def _expected(seed: int, gens: list[float]) -> dict[int, list[float]]:
    """Delivery slots of fresh domain links fed the same frames."""
    out: dict[int, list[float]] = {}
    for n, rng in zip(range(1, N_CAMERAS + 1), camera_rngs(seed, N_CAMERAS), strict=True):
        link = Link("exp:60", rng)
        out[n] = [float(s) for g in gens if (s := link.offer(g)) is not None]
    return out


def test_random_delays_match_the_domain_link_per_camera_and_reseed() -> None:
    clock = SimClock(epoch_s=time.time() - 10.0, time_scale=50.0)  # 1 sim ms = 20 µs wall
    bus = MemoryBus()
    arrivals = Arrivals(bus)
    with TestClient(make_app(bus, clock, delay="exp:60", seed=5)) as client:
        base = math.floor(clock.now_ms() / 30) * 30 - 30 * 400  # frames from the past
        gens = [float(base + 30 * k) for k in range(150)]
        expected = _expected(5, gens)
        for g in gens:
            for n in range(1, N_CAMERAS + 1):
                bus.publish(KEYS.cam_frame(n), frame(n, g))
        total = sum(len(v) for v in expected.values())
        got = arrivals.wait(total)
        for n in range(1, N_CAMERAS + 1):
            assert [m.delivery_ms for _, k, m in got if m.camera_id == n] == expected[n]
        assert expected[1] != expected[2]  # independent streams per camera
        text = client.get("/metrics").text
        for n in range(1, N_CAMERAS + 1):
            assert metric(text, "aoi3d_frames_offered_total", camera=str(n)) == len(gens)
            assert metric(text, "aoi3d_frames_dropped_total", camera=str(n)) == (
                len(gens) - len(expected[n]))
        assert metric(text, "aoi3d_link_delay_seconds_count") == total
        assert 0 < metric(text, "aoi3d_frames_dropped_total", camera="1") < len(gens)

        # a new seed restarts every link's stream (the links are idle: all delivered)
        assert client.put("/channel", json={"seed": 11}).status_code == 200
        start = math.ceil(max(max(v) for v in expected.values()) / 30) * 30
        gens2 = [float(start + 30 * k) for k in range(100)]
        expected2 = _expected(11, gens2)
        for g in gens2:
            for n in range(1, N_CAMERAS + 1):
                bus.publish(KEYS.cam_frame(n), frame(n, g))
        got = arrivals.wait(total + sum(len(v) for v in expected2.values()))[total:]
        for n in range(1, N_CAMERAS + 1):
            assert [m.delivery_ms for _, k, m in got if m.camera_id == n] == expected2[n]
        assert _expected(5, gens2) != expected2


def _bad_pose_frame() -> bytes:
    pose, intr = camera_to_pb(CAMERA)
    pose.c2w[0] = float("nan")
    return pb.Frame(camera_id=1, generation_ms=1.0, pose=pose, intrinsics=intr,
                    image=IMAGE).SerializeToString()


def _wrong_size_frame() -> bytes:
    pose, intr = camera_to_pb(CAMERA)
    intr.width = W + 1
    return pb.Frame(camera_id=1, generation_ms=1.0, pose=pose, intrinsics=intr,
                    image=IMAGE).SerializeToString()


def test_bad_frames_are_counted_and_dropped_and_the_links_keep_working() -> None:
    clock = SimClock(epoch_s=time.time() - 1.0, time_scale=1.0)
    bus = MemoryBus()
    arrivals = Arrivals(bus)
    with TestClient(make_app(bus, clock, delay="const:1")) as client:
        now = clock.now_ms()
        bus.publish(KEYS.cam_frame(1), b"\x0a\xff\xff garbage")
        bus.publish(KEYS.cam_frame(1), frame(1, now)[:40])  # truncated
        bus.publish(KEYS.cam_frame(9), frame(9, now))  # not part of the rig
        bus.publish(KEYS.cam_frame(1), frame(2, now))  # published under another camera's key
        bus.publish(KEYS.cam_frame(1), _bad_pose_frame())
        bus.publish(KEYS.cam_frame(1), _wrong_size_frame())
        bus.publish(KEYS.cam_frame(1), frame(1, now + 1e6))  # from a clock far ahead
        bus.publish(KEYS.cam_frame(2), frame(2, now))  # a good one
        got = arrivals.wait(1)
        settle(0.3)  # a bad frame let through would be delivered by now (40 ms links)
        assert [m.camera_id for _, _, m in got] == [2]
        text = client.get("/metrics").text
        counts = {reason: metric(text, "aoi3d_messages_rejected_total", reason=reason)
                  for reason in ("malformed", "unknown_camera", "key_mismatch", "bad_pose",
                                 "image_size_mismatch", "clock_skew")}
        assert counts == {"malformed": 2, "unknown_camera": 1, "key_mismatch": 1,
                          "bad_pose": 1, "image_size_mismatch": 1, "clock_skew": 1}
        assert metric(text, "aoi3d_frames_offered_total", camera="1") == 0
        assert client.get("/readyz").json() == {"ready": True, "reason": ""}


def test_channel_rest_api_validates_and_applies_changes() -> None:
    clock = SimClock(epoch_s=time.time() - 1.0, time_scale=1.0)
    bus = MemoryBus()
    arrivals = Arrivals(bus)
    with TestClient(make_app(bus, clock, delay="exp:60", per_camera={3: "uniform:20:100"})
                    ) as client:
        body = client.get("/channel").json()
        assert body["delay"] == "exp:60" and body["seed"] == 1
        assert body["per_camera"] == {"3": "uniform:20:100"}
        assert "lognormal:MU:SIGMA" in body["accepted_forms"]
        assert [link["delay"] for link in body["links"]] == ["exp:60", "exp:60",
                                                              "uniform:20:100"]

        bad = client.put("/channel", json={"delay": "poisson:3"})
        assert bad.status_code == 422
        assert "unknown kind 'poisson'" in bad.json()["detail"]
        assert "exp:MEAN" in bad.json()["detail"] and "uniform:LO:HI" in bad.json()["detail"]
        bad = client.put("/channel", json={"delay": "exp:-5"})
        assert bad.status_code == 422 and "> 0" in bad.json()["detail"]
        bad = client.put("/channel", json={"per_camera": {"7": "const:1"}})
        assert bad.status_code == 422 and "1..3" in bad.json()["detail"]
        bad = client.put("/channel", json={"per_camera": {"2": "const"}})
        assert bad.status_code == 422 and "per_camera 2" in bad.json()["detail"]
        assert client.put("/channel", json={"seed": -1}).status_code == 422
        assert client.put("/channel", json={"delays": "exp:1"}).status_code == 422
        assert client.get("/channel").json() == body  # nothing half-applied

        ok = client.put("/channel", json={"delay": "const:5", "per_camera": {"2": "const:3"},
                                          "seed": 9})
        assert ok.status_code == 200, ok.text
        assert ok.json()["delay"] == "const:5" and ok.json()["seed"] == 9
        assert [link["delay"] for link in ok.json()["links"]] == ["const:5", "const:3",
                                                                  "const:5"]
        g = float(math.ceil(clock.now_ms()))
        bus.publish(KEYS.cam_frame(1), frame(1, g))
        bus.publish(KEYS.cam_frame(2), frame(2, g))
        got = arrivals.wait(2)
        assert {m.camera_id: m.delivery_ms - g for _, _, m in got} == {1: 5.0, 2: 3.0}


def test_settings_reject_a_bad_delay_spec_at_startup() -> None:
    with pytest.raises(ValueError, match="Accepted forms"):
        Settings(delay="exp")
    app = create_app(Settings(common=CommonSettings(cameras=2), per_camera={5: "const:1"}),
                     bus=MemoryBus())
    with pytest.raises(ValueError, match="unknown camera"), TestClient(app):
        pass


def test_stop_is_prompt_with_frames_in_flight() -> None:
    clock = SimClock(epoch_s=time.time(), time_scale=0.1)
    bus = MemoryBus()
    client = TestClient(make_app(bus, clock, delay="const:10000"))
    with client:
        bus.publish(KEYS.cam_frame(1), frame(1, clock.now_ms()))
        time.sleep(0.05)
        assert client.get("/channel").json()["links"][0]["in_flight"]
        t0 = time.monotonic()
    assert time.monotonic() - t0 < 2.0
    assert bus.messages(KEYS.edge_frames) == []


def test_a_frame_stamped_ahead_cannot_block_a_link() -> None:
    """A frame stamped 999 ms ahead used to be accepted (skew 1000 sim ms) and hold the
    camera's D/G/1/0 link busy until then: every real frame meanwhile was dropped, nothing
    counted. The skew is now AOI3D_MAX_SKEW_S (0.5 wall s, × time scale in sim ms)."""
    clock = SimClock(epoch_s=time.time(), time_scale=1.0)
    bus = MemoryBus()
    arrivals = Arrivals(bus)
    with TestClient(make_app(bus, clock)) as client:
        g = float(math.ceil(clock.now_ms()) + 5)
        bus.publish(KEYS.cam_frame(1), frame(1, g + 900.0, sequence=1))  # within the old 1 s
        bus.publish(KEYS.cam_frame(1), frame(1, g, sequence=2))
        got = arrivals.wait(1)
        assert got[0][2].sequence == 2  # the real frame went through
        text = client.get("/metrics").text
        assert metric(text, "aoi3d_messages_rejected_total", reason="clock_skew") == 1
        assert metric(text, "aoi3d_frames_dropped_total", camera="1") == 0


# --- channels that change: regimes, traces (the domain's Link, live) ----------------------------


def _expected_on(spec: str, seed: int, start_ms: int, gens: list[float],
                 size: int) -> dict[int, list[float]]:
    """Delivery slots of the domain's links on ``spec`` started at ``start_ms``, fed the
    frames of every camera in (slot, camera) order — the network service's order here."""
    from aoi3d.channel import make_links

    links = make_links(spec, camera_rngs(seed, N_CAMERAS), start_ms=start_ms)
    out: dict[int, list[float]] = {n: [] for n in range(1, N_CAMERAS + 1)}
    for g in gens:
        for n, link in zip(range(1, N_CAMERAS + 1), links, strict=True):
            if (s := link.offer(g, size)) is not None:
                out[n].append(float(s))
    return out


@pytest.mark.parametrize("spec", ["regimes:exp:10@300ms,exp:120@300ms",
                                  "trace:{trace},spread=200", "cell:{trace}"])
def test_a_changing_channel_set_over_rest_matches_the_domain_links(spec: str,
                                                                   tmp_path) -> None:
    trace = tmp_path / "t.up"  # one 1500-byte opportunity every 3 ms, a burst at 200
    trace.write_text("\n".join(str(t) for t in sorted([*range(0, 400, 3), *[200] * 20, 400]))
                     + "\n")
    spec = spec.format(trace=trace)
    clock = SimClock(epoch_s=time.time() - 10.0, time_scale=50.0)
    bus = MemoryBus()
    arrivals = Arrivals(bus)
    with TestClient(make_app(bus, clock, files_roots=[str(tmp_path)], delay="const:1",
                             seed=4)) as client:
        ok = client.put("/channel", json={"delay": spec})
        assert ok.status_code == 200, ok.text
        body = ok.json()
        started = int(body["started_ms"])
        sets = [c for c in body["changes"] if c["cause"] == "set"]
        assert body["delay"] == spec and sets[-1]["delay"] == spec
        assert sets[-1]["time_ms"] == pytest.approx(started, abs=1)
        base = math.floor(started / 30) * 30 - 30 * 50  # before and after the start
        gens = [float(base + 30 * k) for k in range(60)]
        expected = _expected_on(spec, 4, started, gens, len(IMAGE.data))
        for g in gens:
            for n in range(1, N_CAMERAS + 1):
                bus.publish(KEYS.cam_frame(n), frame(n, g))
        got = arrivals.wait(sum(len(v) for v in expected.values()))
        for n in range(1, N_CAMERAS + 1):
            assert [m.delivery_ms for _, k, m in got if m.camera_id == n] == expected[n]
        view = client.get("/channel").json()
        if spec.startswith("regimes"):
            assert view["in_force"] in ("exp:10", "exp:120")
            regimes = [c for c in view["changes"] if c["cause"] == "regime"]
            assert regimes and regimes[0]["time_ms"] == pytest.approx(started + 300, abs=1)
            assert regimes[0]["spec"] == "exp:120"
        assert view["measured_delay_ms"] is None or view["measured_delay_ms"] > 0


def test_a_refused_channel_changes_nothing(tmp_path) -> None:
    clock = SimClock(epoch_s=time.time() - 1.0, time_scale=1.0)
    with TestClient(make_app(MemoryBus(), clock, files_roots=[str(tmp_path), "/no"],
                             delay="regimes:const:5@1s,const:9@1s")) as client:
        body = client.get("/channel").json()
        assert body["in_force"] in ("const:5", "const:9")
        assert any("regimes:SPEC@DUR" in f for f in body["accepted_forms"])
        for bad, why in [("trace:/no/such.up", "cannot read trace"),
                         ("regimes:exp:20", "lacks its duration"),
                         (f"trace:{tmp_path}", "not a file"),
                         ("cell:/no/such.up,spread=1", "cannot read trace"),
                         ("trace:/etc/passwd", "must lie in"),  # never read, nor said if there
                         (f"trace:{tmp_path}/../../etc/hostname", "must lie in")]:
            r = client.put("/channel", json={"delay": bad})
            assert r.status_code == 422 and why in r.json()["detail"], r.text
        trace = tmp_path / "t.up"
        trace.write_text("0\n5\n10\n")
        r = client.put("/channel", json={"per_camera": {"2": f"cell:{trace}"}})
        assert r.status_code == 422 and "default delay" in r.json()["detail"]
        after = client.get("/channel").json()
        assert {k: v for k, v in after.items() if k != "in_force"} == {
            k: v for k, v in body.items() if k != "in_force"}


def test_frames_are_sized_by_their_png_or_as_jpeg_when_configured(tmp_path) -> None:
    from aoi3d.channel import make_links
    from aoi3d.channel.varying import jpeg_bytes
    from services.network.core import NetworkCore

    trace = tmp_path / "t.up"  # one opportunity every 5 ms: a frame's delay is 5 ms a packet
    trace.write_text("\n".join(str(t) for t in range(0, 1001, 5)) + "\n")
    w, h = 64, 48
    cam = Camera(c2w=look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=50.0, fy=50.0,
                 cx=w / 2, cy=h / 2, width=w, height=h)
    rgb = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    image = encode_png(rgb)
    payload = encode_frame(camera_id=1, sequence=0, generation_ms=100.0, scene_time_ms=0.0,
                           camera=cam, image=image)
    spec = f"trace:{trace},spread=0"
    sizes = {"png": len(image.data), "jpeg:10": jpeg_bytes(rgb, 10)}
    assert -(-sizes["png"] // 1500) > -(-sizes["jpeg:10"] // 1500)  # different packet counts
    for encoding, size in sizes.items():
        core = NetworkCore(N_CAMERAS, delay=spec, frame_encoding=encoding)
        _, pending = core.offer(KEYS.cam_frame(1), payload, now_ms=100.0)
        expected = make_links(spec, camera_rngs(1, N_CAMERAS))[0].offer(100.0, size)
        assert pending is not None and pending.delivery_ms == expected
    with pytest.raises(ValueError, match="frame encoding"):
        Settings(frame_encoding="webp")
