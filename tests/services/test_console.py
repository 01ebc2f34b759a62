"""The console service on a MemoryBus: it pairs each render with the truth of the same
simulated time, keeps the quality timeline and the decision in force, serves the images and
pushes its state as Server-Sent Events. (The page itself, in a real browser against a real
pipeline: tests/browser/.)"""

from __future__ import annotations

import io
import json

import numpy as np
from fastapi.testclient import TestClient
from PIL import Image

from services.console.app import create_app
from services.console.core import LAG_RENDERS, ConsoleCore
from services.console.settings import Settings
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from tests.support.console import render, truth
from tests.support.network import CAMERA
from tests.support.waits import wait_for

KEYS = Keys("console")
UPSTREAM = {n: "http://127.0.0.1:9" for n in ("camera", "network", "scheduler", "dispatcher",
                                               "metrics")}  # nothing listens: errors shown


def test_the_console_pairs_renders_with_the_truth_of_their_time() -> None:
    bus = MemoryBus()
    settings = Settings(upstream=UPSTREAM, push_period_s=0.1, poll_period_s=0.2,
                        common=CommonSettings(run_id="console", cameras=3))
    with TestClient(create_app(settings, bus=bus)) as client:
        assert client.get("/render.png").status_code == 404
        bus.publish(KEYS.truth, truth(30.0, 10))
        bus.publish(KEYS.truth, truth(60.0, 200))
        bus.publish(KEYS.render, render(7, 60.0, 190))
        ids = [1, 2, 3]
        bus.publish(KEYS.decision, pb.Decision(
            decision_id=7, time_ms=60.0, camera_ids=ids, aoi_ms=[30.0, 60.0, float("nan")],
            selected=[pb.FrameRef(camera_id=1, generation_ms=30.0)],
            policy="mat:50").SerializeToString())
        bus.publish(KEYS.quality, pb.Quality(decision_id=7, time_ms=60.0, psnr_db=25.0,
                                             ssim=0.8, reward=0.9).SerializeToString())
        state = wait_for(lambda: (s := client.get("/state").json())["quality"] and s)
        assert state["render"]["time_ms"] == 60.0 and state["render"]["truth_time_ms"] == 60.0
        assert state["decision"]["selected"] == [1]
        assert state["decision"]["aoi_ms"] == [30.0, 60.0, None]  # NaN: unknown
        assert state["quality"][0]["psnr_db"] == 25.0 and state["quality"][0]["lpips"] is None
        assert "unreachable" in wait_for(lambda: client.get("/state").json().get("channel",
                                                                                 {}).get("error"))
        got = np.asarray(Image.open(io.BytesIO(client.get("/truth.png").content)))
        assert (got == 200).all()  # the truth of 60 ms, not the one of 30 ms
        diff = np.asarray(Image.open(io.BytesIO(client.get("/diff.png").content)))
        assert diff.shape == (CAMERA.height, CAMERA.width, 3) and diff[..., 0].max() > 0
        with client.stream("GET", "/events") as events:
            for line in events.iter_lines():
                if line.startswith("data: "):
                    assert json.loads(line[6:])["render"]["decision_id"] == 7
                    break
        assert client.get("/api/nowhere/x").status_code == 404
        r = client.put("/api/scheduler/policy", json={"kind": "all"})
        assert r.status_code == 502 and "did not answer" in r.text
        page = client.get("/").text
        assert "/static/console.js" in page and "http" not in page.split("<body>")[1]


def quality(decision_id: int, time_ms: float, *, lag_ms: float | None, psnr: float = 25.0,
            psnr_display: float | None = None, steps: int | None = None) -> bytes:
    q = pb.Quality(decision_id=decision_id, time_ms=time_ms, psnr_db=psnr, ssim=0.8,
                   reward=0.9)
    if lag_ms is not None:
        q.ready_ms = time_ms + lag_ms
    if psnr_display is not None:
        q.display_time_ms = time_ms + (lag_ms or 0.0)
        q.psnr_display_db = psnr_display
    if steps is not None:
        q.render_steps = steps
    return q.SerializeToString()


def test_the_console_shows_the_display_lag_the_display_psnr_and_the_budget() -> None:
    """Issue 40: the lag from decision to display (measured over the recent renders, and the
    scheduler's expectation), the PSNR at display time beside the PSNR at the decision's
    time, and the budget in force, in the state the page draws; the page has the budget
    control."""
    bus = MemoryBus()
    settings = Settings(upstream=UPSTREAM, push_period_s=0.1, poll_period_s=0.2,
                        common=CommonSettings(run_id="console", cameras=3))
    with TestClient(create_app(settings, bus=bus)) as client:
        bus.publish(KEYS.decision, pb.Decision(
            decision_id=9, time_ms=90.0, camera_ids=[1, 2, 3], aoi_ms=[30.0, 60.0, 90.0],
            policy="mat:70@50", budget_steps=50, expected_lag_ms=33.5).SerializeToString())
        for i, lag in enumerate((30.0, 40.0, 35.0)):
            bus.publish(KEYS.quality, quality(i + 1, 30.0 * (i + 1), lag_ms=lag,
                                              psnr=26.0 + i, psnr_display=22.0 + i, steps=50))
        state = wait_for(lambda: len((s := client.get("/state").json())["quality"]) == 3 and s)
        assert state["decision"]["budget_steps"] == 50
        assert state["decision"]["expected_lag_ms"] == 33.5
        assert [q["psnr_display_db"] for q in state["quality"]] == [22.0, 23.0, 24.0]
        assert [q["display_lag_ms"] for q in state["quality"]] == [30.0, 40.0, 35.0]
        assert state["display"] == {
            "display_lag_ms": 35.0, "display_lag_n": 3, "expected_lag_ms": 33.5,
            "psnr_db": 28.0, "psnr_display_db": 24.0, "budget_steps": 50,
            "budget_source": "decision"}
        page = client.get("/").text
        assert 'id="budget"' in page and 'id="display"' in page
        js = client.get("/static/console.js").text
        assert "budget_steps" in js and "psnr_display_db" in js


def test_the_display_summary_takes_the_recent_renders_and_the_trainers_budget() -> None:
    core = ConsoleCore()
    assert core.display() == {"display_lag_ms": None, "display_lag_n": 0,
                              "expected_lag_ms": None, "psnr_db": None,
                              "psnr_display_db": None, "budget_steps": None,
                              "budget_source": None}
    # a decision without a budget: the dispatcher's render_steps is the budget in force
    core.on_decision(pb.Decision(decision_id=1, time_ms=30.0, camera_ids=[1], aoi_ms=[0.0],
                                 policy="mat:70").SerializeToString(), now=1.0)
    core.on_status({"dispatcher": {"render_steps": 20}}, now=1.0)
    got = core.display()
    assert (got["budget_steps"], got["budget_source"]) == (20, "dispatcher")
    assert got["expected_lag_ms"] is None
    # an old regime, then LAG_RENDERS newer renders: the median is the newer ones'
    for i in range(10):
        core.on_quality(quality(i, 30.0 * i, lag_ms=1000.0), now=2.0)
    for i in range(LAG_RENDERS):
        core.on_quality(quality(i, 30.0 * i, lag_ms=40.0 + i % 3), now=3.0)
    got = core.display()
    assert got["display_lag_ms"] == 41.0 and got["display_lag_n"] == LAG_RENDERS
    assert got["psnr_display_db"] is None  # no display score (no truth then): none shown
    # a render of an older metrics service (no ready time): no lag from it
    core.on_quality(quality(99, 30.0, lag_ms=None), now=4.0)
    assert core.display()["display_lag_n"] == LAG_RENDERS - 1
    # a dispatcher that did not answer: no budget known
    core.on_status({"dispatcher": {"error": "dispatcher unreachable"}}, now=5.0)
    assert core.display()["budget_steps"] is None
