"""The camera's, network's and console's cores on their own: no bus, no server, no threads.

Each core takes messages (or a configuration) and a time and returns what to publish; the
workers around them (tests/services/) only run them on the shared runtime.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from aoi3d.scene import SceneConfig, generate_dataset, load_dataset
from services.camera.core import CameraConfigError, CameraCore
from services.console.core import TRUTH_FRAMES, ConsoleCore
from services.kit.codec import decode_frame
from services.kit.keys import Keys
from services.kit.observe import Rejected
from services.kit.pb import aoi3d_pb2 as pb
from services.network.core import ChannelConfigError, NetworkCore
from tests.support.console import render, truth
from tests.support.network import frame

KEYS = Keys("cores")


# ---------------------------------------------------------------- camera
@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    path: Path = tmp_path_factory.mktemp("scene") / "tiny"
    generate_dataset(path, SceneConfig(width=16, height=12, fps=10, duration_s=1.0, n_train=3,
                                       rotor_rpm=20.0, spp=1))
    return load_dataset(path)


def test_a_tick_publishes_the_truth_then_each_active_camera_at_its_time(dataset) -> None:
    core = CameraCore(dataset, KEYS, n_cameras=3, period_ms=30.0, cameras=[3, 1])
    assert core.rig == (1, 2, 3) and core.config.cameras == (1, 3)
    tick = core.tick(4, 120.0, core.config.cameras)
    assert [key for key, _, _ in tick.frames] == [KEYS.truth, KEYS.cam_frame(1),
                                                  KEYS.cam_frame(3)]
    frames = [decode_frame(p) for _, p, _ in tick.frames]
    assert {(f.camera_id, f.sequence, f.generation_ms) for f in frames} == {
        (0, 4, 120.0), (1, 4, 120.0), (3, 4, 120.0)}
    assert not tick.errors and core.ticks == 1 and core.last_tick_ms == 120.0


def test_the_tick_grid_never_repeats_a_tick_and_skips_to_the_newest_due(dataset) -> None:
    core = CameraCore(dataset, KEYS, n_cameras=3, period_ms=30.0)
    assert core.first_tick(now_ms=95.0, period_ms=30.0) == 4  # the first at or after now
    core.tick(4, 120.0, core.config.cameras)
    assert core.first_tick(now_ms=100.0, period_ms=30.0) == 5  # never 4 again
    assert core.catch_up(5, now_ms=200.0, period_ms=30.0) == (6, 1)
    assert core.catch_up(5, now_ms=150.0, period_ms=30.0) == (5, 0)


def test_a_refused_camera_setting_changes_nothing(dataset) -> None:
    core = CameraCore(dataset, KEYS, n_cameras=3)
    before = core.config
    for bad in ({"period_ms": 0.5}, {"period_ms": math.nan}, {"cameras": [0]},
                {"cameras": [9]}):
        with pytest.raises(CameraConfigError):
            core.update(**bad)
        assert core.config == before
    assert core.update(period_ms=50.0, paused=True).period_ms == 50.0


def test_a_bad_frame_file_is_reported_and_skipped_and_the_tick_goes_on(dataset) -> None:
    class Damaged:
        """The dataset, with camera 2's files unreadable."""

        def __getattr__(self, name: str):
            return getattr(dataset, name)

        def frame_png(self, n: int, index: int) -> bytes:
            if n == 2:
                raise OSError("disk gone")
            return dataset.frame_png(n, index)

    core = CameraCore(Damaged(), KEYS, n_cameras=3)
    tick = core.tick(0, 0.0, core.config.cameras)
    assert [n for _, _, n in tick.frames] == [0, 1, 3]
    assert len(tick.errors) == 1 and "camera 2" in tick.errors[0]


# ---------------------------------------------------------------- network
def offered(n: int, gen_ms: float) -> bytes:
    return frame(n, gen_ms)


def test_a_link_delivers_after_its_delay_and_drops_while_busy() -> None:
    core = NetworkCore(2, delay="const:50")
    n, first = core.offer("aoi3d/x/cam/1/frame", offered(1, 0.0), now_ms=0.0)
    assert n == 1 and first is not None and first.delivery_ms == 50.0
    assert core.offer("aoi3d/x/cam/1/frame", offered(1, 30.0), now_ms=30.0) == (1, None)
    _, other = core.offer("aoi3d/x/cam/2/frame", offered(2, 10.0), now_ms=10.0)
    assert other is not None and other.delivery_ms == 60.0
    assert core.pending == 2 and core.next_due_ms() == 50.0
    assert core.pop_due(49.0) == []
    assert [p.camera_id for p in core.pop_due(60.0)] == [1, 2]  # in delivery order
    stats = {s.camera_id: s for s in core.link_stats(60.0)}
    assert (stats[1].offered, stats[1].dropped, stats[1].delivered) == (2, 1, 1)
    assert core.pending == 0 and core.next_due_ms() is None


def test_malformed_mismatched_or_future_frames_are_rejected_and_change_nothing() -> None:
    core = NetworkCore(2, delay="const:50")
    cases = [("aoi3d/x/cam/1/frame", b"\x00garbage", "malformed"),
             ("aoi3d/x/cam/2/frame", offered(1, 0.0), "key_mismatch"),
             ("aoi3d/x/cam/1/frame", offered(1, 5000.0), "clock_skew"),
             ("aoi3d/x/cam/7/frame", offered(7, 0.0), None)]
    for key, payload, reason in cases:
        with pytest.raises(Rejected) as err:
            core.offer(key, payload, now_ms=0.0)
        if reason is not None:
            assert err.value.reason == reason
    assert core.pending == 0 and all(s.offered == 0 for s in core.link_stats(0.0))


def test_a_refused_channel_setting_changes_nothing() -> None:
    core = NetworkCore(2, delay="exp:60")
    before = core.config
    for bad in ({"delay": "nonsense"}, {"per_camera": {9: "const:1"}},
                {"per_camera": {1: "bad"}}, {"seed": -1}):
        with pytest.raises(ValueError):
            core.update(**bad)
        assert core.config == before
    with pytest.raises(ChannelConfigError):
        core.update(seed=True)  # type: ignore[arg-type]
    assert core.update(per_camera={2: "const:5"}).spec_of(2) == "const:5"


def test_the_same_seed_gives_the_same_deliveries() -> None:
    def slots(seed: int) -> list[float]:
        core = NetworkCore(3, delay="exp:60", seed=seed)
        out = []
        for k in range(40):
            for n in (1, 2, 3):
                core.offer(f"aoi3d/x/cam/{n}/frame", offered(n, 30.0 * k), now_ms=30.0 * k)
            out += [p.delivery_ms for p in core.pop_due(30.0 * k)]
        return out

    assert slots(4) == slots(4) and slots(4) != slots(5)


# ---------------------------------------------------------------- console
def test_the_console_pairs_a_render_with_the_truth_of_its_time() -> None:
    core = ConsoleCore(period_ms=30.0)
    core.on_truth(truth(30.0, 10))
    core.on_truth(truth(60.0, 200))
    core.on_render(render(7, 70.0, 190), now=100.0)  # 10 ms after the newest truth frame
    assert core.pair.truth_time_ms == 60.0 and core.pair.decision_id == 7
    got = np.asarray(Image.open(io.BytesIO(core.pair.truth_png)))
    assert (got == 200).all()
    heat = np.asarray(Image.open(io.BytesIO(core.diff_png())))
    assert heat[..., 0].max() > 0 and core.diff_png() is core.diff_png()  # cached per render
    core.on_render(render(8, 200.0, 190), now=101.0)  # no truth within one period
    assert core.pair.truth_png is None and core.diff_png() is None
    assert core.snapshot(now=103.0)["render"]["age_s"] == pytest.approx(2.0)


def test_the_truth_ring_is_bounded() -> None:
    core = ConsoleCore()
    for i in range(TRUTH_FRAMES + 10):
        core.on_truth(truth(30.0 * i, 5))
    assert core.truth_at(0.0) is None and core.truth_at(30.0 * (TRUTH_FRAMES + 9)) is not None


def test_policy_and_delay_changes_mark_the_timeline_which_keeps_its_window() -> None:
    core = ConsoleCore(history_s=100.0)

    def decision(policy: str) -> bytes:
        return pb.Decision(decision_id=1, time_ms=0.0, camera_ids=[1], aoi_ms=[math.nan],
                           policy=policy).SerializeToString()

    def channel(delay: str, delivered: int, offered_: int) -> dict:
        return {"delay": delay, "links": [{"delivered": delivered, "offered": offered_,
                                           "dropped": offered_ - delivered}]}

    core.on_decision(decision("mat:70"), now=0.0)
    core.on_decision(decision("mat:40"), now=10.0)
    core.on_status({"channel": channel("exp:60", 0, 0)}, now=20.0)
    core.on_status({"channel": channel("exp:90", 10, 20)}, now=30.0)
    core.on_quality(pb.Quality(decision_id=1, time_ms=0.0, psnr_db=math.nan, ssim=0.5,
                               reward=0.1).SerializeToString(), now=40.0)
    snap = core.snapshot(now=40.0)
    assert [m["text"] for m in snap["markers"]] == ["policy mat:40", "delay exp:90"]
    assert snap["decision"]["aoi_ms"] == [None] and snap["quality"][0]["psnr_db"] is None
    summary = snap["channel_summary"]
    assert summary["delivered_per_s"] == 1.0 and summary["drop_ratio"] == 0.5
    assert summary["delay_quantiles_ms"]["0.5"] == pytest.approx(60 * math.log(2) * 1.5)
    core.on_status({"channel": {"error": "network unreachable"}}, now=125.0)
    snap = core.snapshot(now=125.0)
    assert [m["text"] for m in snap["markers"]] == ["delay exp:90"]  # 10 s is out of 100 s
    assert snap["channel_summary"] is None and snap["channel"]["error"]


def test_malformed_messages_raise_rejected_and_change_nothing() -> None:
    core = ConsoleCore()
    for handler in (core.on_truth, lambda p: core.on_render(p, 0.0),
                    lambda p: core.on_quality(p, 0.0), lambda p: core.on_decision(p, 0.0)):
        with pytest.raises(Rejected):
            handler(b"\xff\x00 not protobuf")
    assert core.pair is None and core.snapshot(0.0)["quality"] == []


def test_the_console_keeps_the_gamma_each_decision_applied() -> None:
    """Γ over time (issue 32): its own series, one point per change or per GAMMA_EVERY_S, in
    the history window; absent Γ (a policy without one) is kept as null."""
    from services.console.core import GAMMA_EVERY_S

    core = ConsoleCore(history_s=100.0)

    def decision(t: float, gamma: float | None, policy: str = "adaptive:plugin") -> bytes:
        msg = pb.Decision(decision_id=1, time_ms=t, camera_ids=[1], aoi_ms=[30.0],
                          policy=policy)
        if gamma is not None:
            msg.gamma_ms = gamma
        return msg.SerializeToString()

    core.on_decision(decision(0.0, 55.0), now=0.0)
    core.on_decision(decision(30.0, 55.0), now=0.03)  # unchanged, too soon: not kept
    core.on_decision(decision(60.0, 70.0), now=0.06)  # changed: kept
    core.on_decision(decision(90.0, 70.0), now=0.06 + GAMMA_EVERY_S)  # unchanged, due: kept
    core.on_decision(decision(120.0, None, "all"), now=1.0)
    snap = core.snapshot(now=1.0)
    assert [g["gamma_ms"] for g in snap["gamma"]] == [55.0, 70.0, 70.0, None]
    assert snap["decision"]["gamma_ms"] is None and snap["gamma"][-1]["policy"] == "all"
    core.trim(now=100.5)
    assert [g["gamma_ms"] for g in core.snapshot(now=100.5)["gamma"]] == [None]


def test_a_regime_change_marks_the_timeline_and_the_channel_series_keeps_the_delay() -> None:
    core = ConsoleCore(history_s=100.0)
    spec = "regimes:exp:20@10s,exp:200@10s"

    def channel(in_force: str, measured: float | None, delivered: int) -> dict:
        return {"delay": spec, "in_force": in_force, "measured_delay_ms": measured,
                "links": [{"delivered": delivered, "offered": delivered, "dropped": 0}]}

    core.on_status({"channel": channel("exp:20", None, 0)}, now=0.0)
    core.on_status({"channel": channel("exp:20", 21.5, 10)}, now=5.0)
    core.on_status({"channel": channel("exp:200", 150.0, 20)}, now=11.0)
    snap = core.snapshot(now=11.0)
    assert [m["text"] for m in snap["markers"]] == ["channel exp:200"]
    assert snap["markers"][0]["kind"] == "channel"
    series = snap["channel_series"]
    assert [p["measured_delay_ms"] for p in series] == [None, 21.5, 150.0]
    assert [p["in_force_mean_ms"] for p in series] == [20.0, 20.0, 200.0]
    assert snap["channel_summary"]["in_force"] == "exp:200"
    assert snap["channel_summary"]["delay_quantiles_ms"]["0.5"] == pytest.approx(
        200 * math.log(2))
    core.on_status({"channel": {**channel("exp:200", 150.0, 30), "delay": "exp:60",
                                "in_force": "exp:60"}}, now=12.0)
    assert [m["text"] for m in core.snapshot(now=12.0)["markers"]] == [
        "channel exp:200", "delay exp:60"]
