"""Free views and exports through the dispatcher's REST, answered by a real reconstruction worker
on a MemoryBus: two poses give two different images of the asked size, a bad pose a 4xx, the
rate limit a 429 (counted), and ``aoi3d export`` a .ply that trimesh reads with thousands of
coloured points inside the scene box. Every wait is tests/support/waits.py's, scaled by
AOI3D_TEST_TIMEOUT_SCALE, with budgets for a loaded 2-core machine (the first render of a
200-step job can take tens of seconds there)."""

from __future__ import annotations

import io
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from aoi3d.clock import SimClock
from aoi3d.field import GridConfig
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from aoi3d.scene.camera import look_at
from services.dispatcher.app import create_app
from services.dispatcher.settings import Settings
from services.kit.codec import PNG, encode_frame
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.recon.core import ReconCore
from services.recon.runtime import ReconWorker
from services.recon.settings import Settings as ReconSettings
from tests.support.timeouts import SCALE
from tests.support.waits import wait_for

N_TRAIN = 6
PERIOD_MS = 100.0
KEYS = Keys("freeviewtest")
GRID = GridConfig(batch_rays=512, samples_coarse=32, samples_fine=32, fine_from_step=0,
                  grid_sizes=(32,), upsample_steps=(), background_size=(4, 8),
                  render_chunk_rays=4096, tune_malloc=False)
FIRST_RENDER_S = 180.0
"""Budget (scaled) for the first render: a cold 200-step job, on a machine that may be busy."""
POLL_S = 0.1
"""Between two polls of a REST route (a faster poll only takes CPU from the job)."""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=32, height=24, fps=10, duration_s=1.0, n_train=N_TRAIN,
                      rotor_rpm=0.0, spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "s", cfg, processes=1)


def make_app(dataset: SceneDataset, bus: MemoryBus, **overrides):
    common = CommonSettings(run_id=KEYS.run_id, cameras=N_TRAIN, time_scale=10.0,
                            epoch_s=time.time())
    # the default carry (stream): the first job, a cold start, trains 200 steps
    settings = Settings(**{"render_steps": 200, "cold_steps": 200, "common": common,
                           "job_timeout_s": FIRST_RENDER_S * SCALE, **overrides})
    clock = SimClock(settings.common.epoch_s, settings.common.time_scale)
    return create_app(settings, bus=bus, clock=clock, dataset=dataset)


class Worker:
    """One reconstruction worker (the real runtime and core) on a thread."""

    def __init__(self, bus: MemoryBus) -> None:
        settings = ReconSettings(worker_id="w1", max_wait_s=0.3, query_margin_s=2.0,
                                 common=CommonSettings(run_id=KEYS.run_id))
        self.worker = ReconWorker(settings, bus, ReconCore(worker_id="w1", device="cpu",
                                                           configs={"grid": GRID}))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.worker.run, args=(self.stop,), daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=10 * SCALE)


def render_one_decision(bus: MemoryBus, ds: SceneDataset) -> None:
    """Every training camera's frame at 0 ms, and a decision that selects them all."""
    for cam in range(1, N_TRAIN + 1):
        image = pb.Image(encoding=PNG, width=ds.width, height=ds.height,
                         data=ds.frame_png(cam, 0))
        bus.publish(KEYS.edge_frame(cam), encode_frame(
            camera_id=cam, sequence=0, generation_ms=0.0, scene_time_ms=ds.scene_time_ms(0.0),
            camera=ds.cameras[cam], image=image, send_ms=0.0, delivery_ms=40.0))
    ids = list(range(1, N_TRAIN + 1))
    bus.publish(KEYS.decision, pb.Decision(
        decision_id=1, time_ms=100.0, camera_ids=ids, aoi_ms=[100.0] * N_TRAIN,
        selected=[pb.FrameRef(camera_id=c, sequence=0, generation_ms=0.0, aoi_ms=100.0)
                  for c in ids], policy="all").SerializeToString())


def c2w_param(eye: tuple[float, float, float]) -> str:
    m = look_at(np.asarray(eye), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    return ",".join(f"{v:.9g}" for v in m.ravel())


@pytest.fixture
def served(dataset: SceneDataset) -> Iterator[tuple[TestClient, MemoryBus]]:
    bus = MemoryBus()
    with TestClient(make_app(dataset, bus)) as client:
        worker = Worker(bus)
        try:
            render_one_decision(bus, dataset)
            wait_for(lambda: client.get("/render.png").status_code == 200, FIRST_RENDER_S,
                     what="the first render", every_s=POLL_S)
            yield client, bus
        finally:
            worker.close()


def views_total(client: TestClient, outcome: str, kind: str = "view") -> float:
    series = f'aoi3d_dispatcher_views_total{{kind="{kind}",outcome="{outcome}"}}'
    for line in client.get("/metrics").text.splitlines():
        if line.startswith(series + " "):
            return float(line.split()[-1])
    raise AssertionError(f"{series} not exported")


def test_two_poses_give_two_images_of_the_asked_size(served) -> None:
    client, _ = served
    images = []
    for eye in ((0.0, -5.0, 2.0), (4.0, 3.0, 3.0)):
        r = client.get("/render.png", params={"c2w": c2w_param(eye), "width": 40,
                                              "height": 30})
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == "image/png" and r.headers["x-free-view"] == "1"
        assert r.headers["x-decision-id"] == "1" and r.headers["x-worker"] == "w1"
        with Image.open(io.BytesIO(r.content)) as img:
            assert img.size == (40, 30)
            images.append(np.asarray(img.convert("RGB"), dtype=np.int16))
    assert np.abs(images[0] - images[1]).mean() > 2.0
    # the held-out view stays the default (and the scored one)
    r = client.get("/sites/site1/render.png")
    assert r.status_code == 200 and "x-free-view" not in r.headers
    assert views_total(client, "served") == 2


@pytest.mark.parametrize(("c2w", "says"), [
    ("1,2,3", "16 numbers"),
    (",".join(["0"] * 16), "rigid"),
    ("1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1,nan", "16 numbers"),
    ("1,0,0,900,0,1,0,0,0,0,1,0,0,0,0,1", "box diagonals"),
])
def test_a_bad_pose_is_a_4xx_that_says_why(served, c2w: str, says: str) -> None:
    client, _ = served
    r = client.get("/render.png", params={"c2w": c2w})
    assert r.status_code == 422
    assert says in r.json()["detail"]


def test_size_bounds_and_stray_parameters(served) -> None:
    client, _ = served
    r = client.get("/render.png", params={"c2w": c2w_param((0.0, -5.0, 2.0)), "width": 5000})
    assert r.status_code == 422 and "pixels" in r.json()["detail"]
    r = client.get("/render.png", params={"width": 40})
    assert r.status_code == 422 and "c2w" in r.json()["detail"]
    assert views_total(client, "bad_request") >= 1


def test_free_views_are_rate_limited_and_the_refusals_counted(dataset: SceneDataset) -> None:
    bus = MemoryBus()
    app = make_app(dataset, bus, view_rate_per_s=0.01, view_burst=1)
    with TestClient(app) as client:
        # no model yet: 404, counted; it took the one token of the burst
        r = client.get("/render.png", params={"c2w": c2w_param((0.0, -5.0, 2.0))})
        assert r.status_code == 404 and "no model" in r.json()["detail"]
        r = client.get("/render.png", params={"c2w": c2w_param((0.0, -5.0, 2.0))})
        assert r.status_code == 429
        assert views_total(client, "rate_limited") == 1
        assert views_total(client, "no_model") == 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_aoi3d_export_writes_a_ply_trimesh_reads(dataset: SceneDataset, tmp_path: Path) -> None:
    trimesh = pytest.importorskip("trimesh")
    import uvicorn
    from typer.testing import CliRunner

    from aoi3d_cli import app as cli

    bus = MemoryBus()
    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(make_app(dataset, bus), host="127.0.0.1",
                                           port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    worker = None
    try:
        wait_for(lambda: server.started, 60.0, what="the dispatcher's server", every_s=POLL_S)
        worker = Worker(bus)
        render_one_decision(bus, dataset)
        import httpx
        wait_for(lambda: httpx.get(f"http://127.0.0.1:{port}/render.png",
                                   timeout=30 * SCALE).status_code == 200,
                 FIRST_RENDER_S, what="the first render", every_s=POLL_S,
                 tolerate=(httpx.HTTPError,))
        out = tmp_path / "model.ply"
        result = CliRunner().invoke(cli, ["export", "--site", "site1", "--out", str(out),
                                          "--resolution", "96",
                                          "--dispatcher", f"http://127.0.0.1:{port}"])
        assert result.exit_code == 0, result.output
        cloud = trimesh.load(out)
        assert isinstance(cloud, trimesh.PointCloud)
        points = np.asarray(cloud.vertices)
        assert len(points) >= 2000, len(points)
        lo, hi = np.asarray(dataset.aabb)
        assert np.all(points >= lo - 1e-4) and np.all(points <= hi + 1e-4)
        colours = np.asarray(cloud.colors)[:, :3]
        assert len(np.unique(colours, axis=0)) > 50
        mesh_out = tmp_path / "model-mesh.ply"
        result = CliRunner().invoke(cli, ["export", "--out", str(mesh_out), "--mesh",
                                          "--resolution", "48", "--dispatcher",
                                          f"http://127.0.0.1:{port}"])
        assert result.exit_code == 0, result.output
        mesh = trimesh.load(mesh_out)
        assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) > 100
        result = CliRunner().invoke(cli, ["export", "--site", "nosuch", "--out",
                                          str(tmp_path / "x.ply"), "--dispatcher",
                                          f"http://127.0.0.1:{port}"])
        assert result.exit_code == 1 and "404" in result.output
    finally:
        if worker is not None:
            worker.close()
        server.should_exit = True
        thread.join(timeout=10 * SCALE)


def test_a_worker_serves_the_newest_view_request_and_answers_the_older_busy() -> None:
    from services.kit.membus import MemoryQuery

    bus = MemoryBus()
    settings = ReconSettings(worker_id="w9", common=CommonSettings(run_id=KEYS.run_id))
    worker = ReconWorker(settings, bus, ReconCore(worker_id="w9", device="cpu",
                                                  configs={"grid": GRID}))
    req = pb.ViewRequest(site="site1", format="png").SerializeToString()
    older, newer = MemoryQuery("k", req), MemoryQuery("k", req)
    worker._on_view(older)
    worker._on_view(newer)  # no view thread yet: the older waits, and is replaced
    assert older.wait(5 * SCALE) and pb.ViewReply.FromString(older.answer).reason == "busy"
    stop = threading.Event()
    thread = threading.Thread(target=worker._serve_views, args=(stop,), daemon=True)
    thread.start()
    try:
        assert newer.wait(30 * SCALE)
        reply = pb.ViewReply.FromString(newer.answer)
        assert reply.reason == "no_model" and "no model of site" in reply.error
    finally:
        stop.set()
        thread.join(timeout=5 * SCALE)
