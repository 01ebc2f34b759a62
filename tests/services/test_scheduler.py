"""The scheduler service: AoI tracking of delivered frames, decisions, /policy, /aoi, /metrics.

Most tests drive the decision thread with a manual clock (the test sets the sim time), so
every decision's AoI vector and selection can be asserted exactly; one runs on a fast real
clock.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from aoi3d.clock import SimClock
from services.kit.codec import encode_png
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.scheduler.app import create_app
from services.scheduler.settings import Settings
from tests.support.metrics import value
from tests.support.scheduler import (
    KEYS,
    N_CAMERAS,
    PERIOD_MS,
    RUN,
    Harness,
    ManualWall,
    decisions,
    frame,
)
from tests.support.timeouts import SCALE
from tests.support.waits import settle, wait_for


def settings(policy: str = "all", cameras: int = N_CAMERAS, period_ms: float = PERIOD_MS
             ) -> Settings:
    return Settings(policy=policy, decision_period_ms=period_ms,
                    common=CommonSettings(run_id=RUN, cameras=cameras))


@pytest.fixture
def make_harness() -> Iterator[Callable[..., Harness]]:
    clients: list[TestClient] = []

    def make(policy: str = "all", start_ms: float = 10.0, cameras: int = N_CAMERAS) -> Harness:
        """Started at ``start_ms``: the first decision comes at the next multiple of 30."""
        wall = ManualWall(start_ms)
        bus = MemoryBus()
        app = create_app(settings(policy, cameras), bus=bus,
                         clock=SimClock(epoch_s=0.0, time_scale=1.0, wall=wall))
        client = TestClient(app)
        client.__enter__()
        clients.append(client)
        return Harness(client, bus, wall)

    yield make
    for client in clients:
        client.__exit__(None, None, None)


def aoi_list(decision: pb.Decision) -> list[float | None]:
    return [None if math.isnan(a) else a for a in decision.aoi_ms]


# ---------------------------------------------------------------- decisions
def test_decisions_follow_delivery_times_and_the_policy(make_harness) -> None:
    h = make_harness("all")
    first = h.decide_at(30.0)
    assert first.decision_id == 1
    assert list(first.camera_ids) == [1, 2, 3, 4]
    assert aoi_list(first) == [None] * 4 and len(first.selected) == 0
    assert first.policy == "all"

    h.put(KEYS.edge_frame(1), frame(1, 30.0, 50.0))
    h.put(KEYS.edge_frame(2), frame(2, 30.0, 75.0))   # delivered after t = 60: held back
    h.put(KEYS.edge_frame(3), frame(3, 60.0, 80.0))
    d60 = h.decide_at(60.0)
    assert d60.decision_id == 2
    assert aoi_list(d60) == [30.0, None, None, None]
    assert [(r.camera_id, r.sequence, r.generation_ms, r.aoi_ms) for r in d60.selected] == [
        (1, 1, 30.0, 30.0)]

    h.put(KEYS.edge_frame(1), frame(1, 0.0, 85.0, sequence=99))  # older: U_1 stays 30
    d90 = h.decide_at(90.0)
    assert aoi_list(d90) == [60.0, 60.0, 30.0, None]
    assert [(r.camera_id, r.sequence, r.aoi_ms) for r in d90.selected] == [
        (1, 1, 60.0), (2, 1, 60.0), (3, 2, 30.0)]

    # GET /aoi: the vector now, null for the unknown camera
    h.wall.set_ms(105.0)
    body = h.client.get("/aoi").json()
    assert body["camera_ids"] == [1, 2, 3, 4]
    assert body["time_ms"] == pytest.approx(105.0)
    assert body["aoi_ms"][:3] == pytest.approx([75.0, 75.0, 45.0])
    assert body["aoi_ms"][3] is None and body["newest_ms"][3] is None
    assert body["newest_ms"][:3] == [30.0, 30.0, 60.0]

    last = h.client.get("/decision").json()
    assert last["decision_id"] == d90.decision_id and last["time_ms"] == 90.0
    assert last["aoi_ms"][3] is None
    assert [s["camera_id"] for s in last["selected"]] == [1, 2, 3]


def test_mat_zero_selects_none_large_mat_selects_every_known_camera(make_harness) -> None:
    h = make_harness("mat:0")
    h.decide_at(30.0)
    for cam, gen, dlv in ((1, 0.0, 1.0), (2, 0.0, 29.0), (3, 30.0, 31.0)):
        h.put(KEYS.edge_frame(cam), frame(cam, gen, dlv))
    d = h.decide_at(60.0)
    assert aoi_list(d) == [60.0, 60.0, 30.0, None]
    assert len(d.selected) == 0 and d.policy == "mat:0"

    r = h.client.put("/policy", json={"kind": "mat", "mat_ms": 1e9})
    assert r.status_code == 200, r.text
    d = h.decide_at(90.0)
    assert d.policy == "mat:1000000000"
    assert [s.camera_id for s in d.selected] == [1, 2, 3]  # camera 4 has no AoI yet

    h.client.put("/policy", json={"kind": "mat", "mat_ms": 61})
    d = h.decide_at(120.0)  # AoI [120, 120, 90]: none < 61
    assert len(d.selected) == 0
    h.put(KEYS.edge_frame(2), frame(2, 90.0, 100.0))
    d = h.decide_at(150.0)  # AoI [150, 60, 120, nan]
    assert [s.camera_id for s in d.selected] == [2]

    h.client.put("/policy", json={"kind": "freshest", "k": 2})
    d = h.decide_at(180.0)  # AoI [180, 90, 150, nan]
    assert d.policy == "freshest:2"
    assert sorted(s.camera_id for s in d.selected) == [2, 3]


def test_decisions_run_on_a_real_fast_clock_and_stop_promptly() -> None:
    bus = MemoryBus()
    period_ms = 200.0  # time scale 20: one decision per 10 ms wall
    app = create_app(settings("all", period_ms=period_ms), bus=bus,
                     clock=SimClock(epoch_s=time.time(), time_scale=20.0))
    with TestClient(app) as client:
        bus.publish(KEYS.edge_frame(2), frame(2, 0.0, 1.0))
        wait_for(lambda: len(decisions(bus)) >= 15)
        assert client.get("/readyz").status_code == 200
        t0 = time.monotonic()
    stop_s = time.monotonic() - t0
    assert stop_s < 2.0 * SCALE
    ds = decisions(bus)
    ids = [d.decision_id for d in ds]
    assert ids == list(range(1, len(ds) + 1))
    times = [d.time_ms for d in ds]
    assert all(t % period_ms == 0 for t in times)
    assert all(b > a for a, b in itertools.pairwise(times))
    assert any(s.camera_id == 2 for s in ds[-1].selected)
    count = len(ds)
    settle(0.3)  # ten decision periods: a live thread would decide again
    assert len(decisions(bus)) == count  # the thread is gone


def test_first_decision_comes_at_the_next_epoch(make_harness) -> None:
    h = make_harness("all")
    assert h.client.get("/decision").status_code == 404
    r = h.client.get("/decision")
    assert r.status_code == 404 and "no decision" in r.json()["detail"]
    d = h.decide_at(30.0)
    assert d.decision_id == 1


# ---------------------------------------------------------------- /policy
def test_policy_get_and_put_round_trip(make_harness) -> None:
    h = make_harness("mat:51", cameras=8)
    got = h.client.get("/policy").json()
    assert got["kind"] == "mat" and got["mat_ms"] == 51 and got["spec"] == "mat:51"
    assert "freshest:<k>" in got["accepted_forms"]
    for body, spec in (({"kind": "mat", "mat_ms": 51}, "mat:51"), ({"kind": "all"}, "all"),
                       ({"kind": "freshest", "k": 6}, "freshest:6"),
                       ({"kind": "mat", "mat_ms": 0}, "mat:0"),
                       ({"kind": "freshest", "k": 8}, "freshest:8")):
        r = h.client.put("/policy", json=body)
        assert r.status_code == 200, r.text
        assert r.json()["spec"] == spec
        assert h.client.get("/policy").json()["spec"] == spec
    # a GET body can be PUT back as it is
    state = h.client.get("/policy").json()
    assert h.client.put("/policy", json=state).json()["spec"] == "freshest:8"
    d = h.decide_at(30.0)
    assert d.policy == "freshest:8"


@pytest.mark.parametrize(("body", "expect"), [
    ({"kind": "mat", "mat_ms": -1}, "mat_ms must be >= 0"),
    ({"kind": "mat"}, "mat_ms"),
    ({"kind": "ppo2"}, "unknown kind 'ppo2'"),
    ({"kind": "freshest", "k": 9}, "0..8"),
    ({"kind": "freshest", "k": -1}, "k must be >= 0"),
    ({"kind": "all", "mat_ms": 3}, "does not take"),
    ({"kind": "freshest", "k": 2.5}, "int"),
    ({"mat_ms": 3}, "kind"),
])
def test_bad_policies_are_rejected_with_a_clear_422(make_harness, body, expect) -> None:
    h = make_harness("all", cameras=8)
    r = h.client.put("/policy", json=body)
    assert r.status_code == 422, r.text
    assert expect in r.text
    assert h.client.get("/policy").json()["spec"] == "all"  # unchanged


def test_a_budget_is_taken_live_and_travels_in_the_decision(make_harness) -> None:
    h = make_harness("all", cameras=8)
    r = h.client.put("/policy", json={"kind": "mat", "mat_ms": 70, "budget_steps": 25})
    assert r.status_code == 200, r.text
    assert (r.json()["spec"], r.json()["budget_steps"]) == ("mat:70@25", 25)
    d = h.decide_at(30.0)
    assert d.policy == "mat:70@25" and d.HasField("budget_steps") and d.budget_steps == 25
    got = h.client.get("/decision").json()
    assert got["budget_steps"] == 25
    before = h.client.get("/policy").json()
    for bad in (0, 100_001, "25", True, 2.5):  # refused: nothing changes
        r = h.client.put("/policy", json={"kind": "mat", "mat_ms": 40, "budget_steps": bad})
        assert r.status_code == 422, (bad, r.text)
        assert h.client.get("/policy").json() == before
    r = h.client.put("/policy", json={"kind": "deadline", "mat_ms": 70, "deadline_ms": 60,
                                      "budget_steps": 25})
    assert r.status_code == 422 and "chooses each decision's budget" in r.text
    assert h.client.get("/policy").json() == before


def test_nan_mat_is_rejected(make_harness) -> None:
    h = make_harness("all")
    r = h.client.put("/policy", content=b'{"kind": "mat", "mat_ms": NaN}',
                     headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert "NaN is not a valid JSON number" in r.text  # services.kit.guard, before the route
    assert h.client.get("/policy").json()["spec"] == "all"  # unchanged


def test_bad_startup_policy_fails_fast() -> None:
    with pytest.raises(ValueError, match="Accepted forms"):
        settings("mat:-3")
    with pytest.raises(ValueError, match=r"0\.\.4"):
        create_app(settings("freshest:5"), bus=MemoryBus())


# ---------------------------------------------------------------- bad input and metrics
def test_bad_frames_are_counted_and_dropped(make_harness) -> None:
    h = make_harness("all")
    h.decide_at(30.0)
    good = frame(1, 0.0, 10.0)
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    skew = np.eye(4)
    skew[0, 1] = 0.5
    bad_pose_msg = pb.Frame.FromString(good)
    bad_pose_msg.pose.c2w[:] = list(skew.ravel())
    nan_msg = pb.Frame.FromString(good)
    nan_msg.pose.c2w[:] = list(nan_pose.ravel())
    for key, payload in (
        (KEYS.edge_frame(1), b"\x08\xff\xff garbage"),
        (KEYS.edge_frame(1), good[: len(good) // 2]),
        (KEYS.edge_frame(9), frame(9, 0.0, 10.0)),  # camera 9 is not in the rig (N = 4)
        (KEYS.edge_frame(1), nan_msg.SerializeToString()),
        (KEYS.edge_frame(1), bad_pose_msg.SerializeToString()),
        (KEYS.edge_frame(1), frame(1, 0.0, 10.0, image=encode_png(np.zeros((5, 5, 3),
                                                                           np.uint8)))),
        (KEYS.edge_frame(2), frame(2, 20.0, 10.0)),  # delivered before it was generated
    ):
        h.put(key, payload)
    h.put(KEYS.edge_frame(3), frame(3, 0.0, 10.0))
    d = h.decide_at(60.0)
    assert aoi_list(d) == [None, None, 60.0, None]  # only the good frame counted

    text = h.client.get("/metrics").text
    rejected = {reason: value(text, f'aoi3d_messages_rejected_total{{reason="{reason}"}}')
                for reason in ("malformed", "unknown_camera", "bad_pose",
                               "image_size_mismatch", "bad_time")}
    assert rejected["unknown_camera"] == 1
    assert rejected["bad_pose"] == 2
    assert rejected["image_size_mismatch"] == 1
    assert rejected["bad_time"] == 1
    assert rejected["malformed"] is not None and rejected["malformed"] >= 1
    assert sum(v or 0 for v in rejected.values()) == 7
    assert h.decide_at(90.0).decision_id == 3  # still deciding


def test_metrics_export_aoi_selection_and_decision_count(make_harness) -> None:
    h = make_harness("mat:40")
    h.decide_at(30.0)
    h.put(KEYS.edge_frame(1), frame(1, 0.0, 5.0))
    h.put(KEYS.edge_frame(2), frame(2, 30.0, 35.0))
    h.decide_at(60.0)  # AoI [60, 30, nan, nan], MAT 40 selects camera 2
    text = h.client.get("/metrics").text
    assert value(text, 'aoi3d_aoi_seconds{camera="1"}') == pytest.approx(0.06)
    assert value(text, 'aoi3d_aoi_seconds{camera="2"}') == pytest.approx(0.03)
    assert value(text, 'aoi3d_aoi_seconds{camera="3"}') is None  # unknown: no series
    assert value(text, "aoi3d_cameras_selected") == 1
    assert value(text, "aoi3d_camera_selections_total") == 1  # none at 30 ms, one at 60 ms
    assert value(text, "aoi3d_decisions_total") == 2
    assert value(text, 'aoi3d_frames_received_total{camera="2"}') == 1
    ready = h.client.get("/readyz")
    assert ready.status_code == 200 and "2 of 4" in ready.json()["reason"]


def test_the_policy_in_force_is_a_series(make_harness) -> None:
    h = make_harness("mat:70")
    text = h.client.get("/metrics").text
    assert 'aoi3d_policy_info{kind="mat",site="site1",spec="mat:70"} 1.0' in text
    assert value(text, "aoi3d_policy_mat_seconds") == pytest.approx(0.07)
    assert h.client.put("/policy", json={"kind": "freshest", "k": 2}).status_code == 200
    text = h.client.get("/metrics").text
    assert 'aoi3d_policy_info{kind="freshest",site="site1",spec="freshest:2"} 1.0' in text
    assert "mat:70" not in text.split("aoi3d_policy_info")[-1].splitlines()[0]
    assert math.isnan(value(text, "aoi3d_policy_mat_seconds"))
