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
from services.console.settings import Settings
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from tests.support.console import render, truth
from tests.support.network import CAMERA
from tests.support.waits import wait_for

KEYS = Keys("console")
UPSTREAM = {n: "http://127.0.0.1:9" for n in ("camera", "network", "scheduler", "trainer",
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
