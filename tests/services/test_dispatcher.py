"""The dispatcher service (the pool's dispatcher) and real reconstruction workers on one MemoryBus:
real frames and decisions in, renders out, each decision to exactly one worker."""

from __future__ import annotations

import io
import math
import os
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from pydantic import ValidationError

from aoi3d.clock import SimClock
from aoi3d.field import BACKENDS
from aoi3d.scene import SceneDataset
from services.dispatcher.app import create_app
from services.dispatcher.settings import Settings
from services.kit.codec import decode_image, decode_render
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.metrics.ledger import Outcome, decode_outcome
from services.recon.core import ReconCore
from services.recon.runtime import ReconWorker
from services.recon.settings import Settings as ReconSettings
from tests.support.dispatcher import (
    CONFIGS,
    KEYS,
    N_TRAIN,
    decision_payload,
    frame_payload,
    make_settings,
    metric,
    publish_frames,
)
from tests.support.timeouts import timeout_scale
from tests.support.waits import settle, wait_for

TIMEOUT_SCALE = timeout_scale()








@pytest.fixture
def bus() -> MemoryBus:
    return MemoryBus()


@pytest.fixture
def client(dataset: SceneDataset, bus: MemoryBus) -> Iterator[TestClient]:
    settings = make_settings()
    clock = SimClock(settings.common.epoch_s, settings.common.time_scale)
    app = create_app(settings, bus=bus, clock=clock, dataset=dataset)
    with TestClient(app) as c:
        yield c


class Pool:
    """Reconstruction workers (the real runtime and core) on threads of this process."""

    def __init__(self, bus: MemoryBus) -> None:
        self.bus = bus
        self.workers: list[tuple[ReconWorker, threading.Event, threading.Thread]] = []

    def add(self, worker_id: str) -> ReconWorker:
        settings = ReconSettings(worker_id=worker_id, max_wait_s=0.3, query_margin_s=2.0,
                                 common=CommonSettings(run_id=KEYS.run_id))
        core = ReconCore(worker_id=worker_id, device="cpu", configs=CONFIGS)
        worker = ReconWorker(settings, self.bus, core)
        stop = threading.Event()
        thread = threading.Thread(target=worker.run, args=(stop,), daemon=True)
        thread.start()
        self.workers.append((worker, stop, thread))
        return worker

    def stop(self) -> None:
        for _, stop, _ in self.workers:
            stop.set()
        for _, _, thread in self.workers:
            thread.join(timeout=10 * TIMEOUT_SCALE)


@pytest.fixture
def pool(bus: MemoryBus) -> Iterator[Pool]:
    p = Pool(bus)
    yield p
    p.stop()


# ------------------------------------------------------------------------ helpers










def renders(bus: MemoryBus) -> list[pb.Render]:
    """The renders the workers published (not the test's own bad ones)."""
    msgs = [pb.Render.FromString(p) for p in bus.messages(KEYS.render)]
    return [m for m in msgs if m.worker_id]


# ------------------------------------------------------------------------ tests
def test_a_decision_is_rendered_by_one_worker_from_its_own_frames(
        client: TestClient, bus: MemoryBus, pool: Pool, dataset: SceneDataset) -> None:
    pool.add("w1")
    wait_for(lambda: client.get("/workers").json()["workers"], what="the worker to join")
    publish_frames(bus, dataset, 0.0)
    publish_frames(bus, dataset, 100.0)
    # Cameras 1-3 at 100 ms are delivered; camera 4's frame at 900 ms never was.
    refs = [(1, 100.0), (2, 100.0), (3, 100.0), (4, 900.0)]
    bus.publish(KEYS.decision, decision_payload(7, 200.0, refs, policy="mat:51"))

    wait_for(lambda: renders(bus), what="a render")
    render, camera = decode_render(bus.messages(KEYS.render)[-1])
    assert (render.decision_id, render.time_ms, render.worker_id) == (7, 200.0, "w1")
    # the default carry, stream; a worker's first job is a cold start (cold_steps)
    assert render.backend == "grid" and render.n_views == 3 and render.carry == "stream"
    assert render.render_steps == render.training_step == 20 and not render.warm_start
    assert sorted(render.frame_generation_ms) == [100.0] * 3
    assert math.isfinite(render.loss) and render.loss > 0
    assert camera == dataset.cameras[dataset.heldout_id]
    rgb = decode_image(render.image)
    assert rgb.shape == (dataset.height, dataset.width, 3) and rgb.dtype == np.uint8

    status = wait_for(lambda: (s := client.get("/status").json())["pool"]["rendered"] == 1
                      and s, what="the render reported")
    assert status["n_views"] == 3 and status["frames_missing"] == 1
    assert status["decision"]["decision_id"] == 7 and status["decision"]["n_missing"] == 1
    assert status["decision"]["policy"] == "mat:51"
    assert status["backend"] == "grid" and status["backends"] == sorted(BACKENDS)
    assert status["device"] == "cpu" and status["renders"] == 1 and status["steps"] == 20
    assert status["frames_buffered"] == status["frames_received"] == 2 * N_TRAIN
    p = status["pool"]
    assert (p["decisions"], p["assigned"], p["rendered"], p["superseded"]) == (1, 1, 1, 0)
    assert p["lost"] == {} and p["in_flight"] == 0 and p["rendered_fraction"] == 1.0
    assert p["fresh_fraction"] == 0.5 and p["waited_fresh"] == 0  # the default; one decision
    (w,) = p["workers"]
    assert w["worker_id"] == "w1" and w["rendered"] == 1 and w["pid"] == os.getpid()

    assert metric(client, "aoi3d_renders_total", 'site="site1"') == 1
    assert metric(client, "aoi3d_dispatcher_steps_total", 'site="site1"') == 20
    assert metric(client, "aoi3d_dispatcher_views", 'site="site1"') == 3
    assert metric(client, "aoi3d_dispatcher_frames_missing_total", 'site="site1"') == 1
    assert metric(client, "aoi3d_pool_workers") == 1
    assert metric(client, "aoi3d_pool_decisions_total", 'outcome="rendered",site="site1"') == 1
    assert metric(client, "aoi3d_pool_wait_seconds_count") == 1
    assert math.isfinite(metric(client, "aoi3d_dispatcher_loss", 'site="site1"'))
    assert metric(client, "aoi3d_pool_worker_renders", 'worker="w1"') == 1

    # An older or repeated decision is rejected, not offered.
    bus.publish(KEYS.decision, decision_payload(7, 200.0, [(1, 100.0)]))
    assert metric(client, "aoi3d_messages_rejected_total", 'reason="stale_decision"') == 1
    assert client.get("/status").json()["pool"]["decisions"] == 1


def test_two_workers_share_the_decisions_and_none_is_rendered_twice(
        client: TestClient, bus: MemoryBus, pool: Pool, dataset: SceneDataset) -> None:
    pool.add("w1")
    pool.add("w2")
    wait_for(lambda: len(client.get("/workers").json()["workers"]) == 2, what="two workers")
    publish_frames(bus, dataset, 0.0)
    for i in range(1, 13):
        bus.publish(KEYS.decision, decision_payload(i, 100.0 * i, [(1, 0.0), (2, 0.0)]))
        time.sleep(0.05)
    p = wait_for(lambda: (p := client.get("/workers").json())["in_flight"] == 0
                 and not p["pending"] and p, what="the pool to drain")
    ids = [r.decision_id for r in renders(bus)]
    assert len(ids) == len(set(ids)) == p["rendered"]  # never twice
    assert p["rendered"] + p["superseded"] + sum(p["lost"].values()) == 12
    assert 12 in ids  # the newest is always done
    assert {r.worker_id for r in renders(bus)} <= {"w1", "w2"}


def test_a_worker_gone_mid_job_loses_only_its_decision(
        client: TestClient, bus: MemoryBus, pool: Pool, dataset: SceneDataset) -> None:
    # a worker that takes a job and vanishes (its token undeclared, as when its session dies)
    token = bus.declare_token(KEYS.pool_worker("doomed"))
    answer = []
    asker = threading.Thread(target=lambda: answer.append(bus.query(
        KEYS.work, pb.WorkRequest(worker_id="doomed", max_wait_s=5.0).SerializeToString(),
        timeout_s=10.0)))
    asker.start()
    wait_for(lambda: client.get("/workers").json()["workers"], what="the doomed worker")
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0)]))
    asker.join(timeout=10)
    job = pb.WorkReply.FromString(answer[0]).job
    assert job.decision.decision_id == 1 and len(job.frames) == 1 and job.render_steps == 20
    token.undeclare()
    p = client.get("/workers").json()
    assert p["lost"] == {"worker_died": 1} and p["workers"] == []
    assert metric(client, "aoi3d_pool_decisions_lost_total", 'reason="worker_died"') == 1
    wait_for(lambda: [(o.decision_id, o.state, o.reason) for o in outcomes(bus)]
             == [(1, "lost", "worker_died")], what="its Outcome for the ledger")
    # the pool goes on with a new worker
    pool.add("w2")
    bus.publish(KEYS.decision, decision_payload(2, 200.0, [(1, 0.0)]))
    wait_for(lambda: any(r.decision_id == 2 for r in renders(bus)), what="decision 2 rendered")
    assert [r.decision_id for r in renders(bus)] == [2]


def outcomes(bus: MemoryBus) -> list[Outcome]:
    """The Outcomes published, as the ledger decodes them (the reason as its label)."""
    return [decode_outcome(p, KEYS.site) for p in bus.messages(KEYS.outcome)]


def test_a_decisions_budget_is_the_steps_its_job_trains(
        client: TestClient, bus: MemoryBus, pool: Pool, dataset: SceneDataset) -> None:
    """A Decision with a budget (a policy's '@<steps>') becomes a Job of that many
    render_steps, and the worker trains exactly that; one without gets the pool's."""
    token = bus.declare_token(KEYS.pool_worker("asker"))  # a worker that asks, to see the Job

    def job_of(decision: bytes) -> pb.Job:
        answer: list[bytes] = []
        asker = threading.Thread(target=lambda: answer.append(bus.query(
            KEYS.work, pb.WorkRequest(worker_id="asker", max_wait_s=5.0).SerializeToString(),
            timeout_s=10.0)))
        asker.start()
        wait_for(lambda: client.get("/workers").json()["workers"], what="the asking worker")
        bus.publish(KEYS.decision, decision)
        asker.join(timeout=10 * TIMEOUT_SCALE)
        return pb.WorkReply.FromString(answer[0]).job

    publish_frames(bus, dataset, 0.0)
    job = job_of(decision_payload(1, 100.0, [(1, 0.0)], "mat:70@7", budget_steps=7))
    assert job.decision.decision_id == 1 and job.render_steps == 7
    assert job.decision.budget_steps == 7  # the decision travels with it
    job = job_of(decision_payload(2, 200.0, [(1, 0.0)], "mat:70"))
    assert job.decision.decision_id == 2 and job.render_steps == 20  # the pool's
    assert not job.decision.HasField("budget_steps")
    token.undeclare()

    # a real worker trains the job's budget: its render says so. Under the default carry
    # (stream) its first job is a cold start, which trains the cold budget whatever the
    # decision's; the warm starts after it train each decision's budget, else the pool's
    pool.add("w1")
    bus.publish(KEYS.decision, decision_payload(3, 300.0, [(1, 0.0), (2, 0.0)], "all@5",
                                                budget_steps=5))
    r = wait_for(lambda: next((r for r in renders(bus) if r.decision_id == 3), None),
                 what="decision 3 rendered")
    assert (r.carry, r.render_steps) == ("stream", 20)  # cold: cold_steps
    bus.publish(KEYS.decision, decision_payload(4, 400.0, [(1, 0.0), (2, 0.0)], "all@5",
                                                budget_steps=5))
    r = wait_for(lambda: next((r for r in renders(bus) if r.decision_id == 4), None),
                 what="decision 4 rendered")
    assert (r.carry, r.render_steps) == ("stream", 5)  # warm: the decision's budget
    bus.publish(KEYS.decision, decision_payload(5, 500.0, [(1, 0.0), (2, 0.0)]))
    r = wait_for(lambda: next((r for r in renders(bus) if r.decision_id == 5), None),
                 what="decision 5 rendered")
    assert (r.carry, r.render_steps) == ("stream", 20)  # warm, no budget: the pool's


def test_decisions_ended_without_a_render_are_told_to_the_ledger(
        client: TestClient, bus: MemoryBus, dataset: SceneDataset) -> None:
    """No worker: each newer decision supersedes the pending one; a decision older than the
    one in force is refused; ids skipped are not received. Each gets one Outcome on the
    site's outcome key."""
    publish_frames(bus, dataset, 0.0)
    for i in (1, 2, 3):
        bus.publish(KEYS.decision, decision_payload(i, 100.0 * i, [(1, 0.0)]))
    bus.publish(KEYS.decision, decision_payload(4, 50.0, [(1, 0.0)]))
    bus.publish(KEYS.decision, decision_payload(7, 700.0, [(1, 0.0)]))  # 5, 6 never came
    wait_for(lambda: len(outcomes(bus)) == 6, what="six Outcomes")
    got = [(o.decision_id, o.state, o.reason, o.detail, o.site) for o in outcomes(bus)]
    assert got == [(1, "skipped", "superseded", "", "site1"),
                   (2, "skipped", "superseded", "", "site1"),
                   (4, "lost", "refused", "stale_decision", "site1"),
                   (5, "lost", "not_received", "", "site1"),
                   (6, "lost", "not_received", "", "site1"),
                   (3, "skipped", "superseded", "", "site1")]
    settle(1.0)  # nothing more: decision 7 is pending, not ended (> the workers' 0.3 s wait)
    assert len(outcomes(bus)) == 6


def test_render_png_404_then_200(client: TestClient, bus: MemoryBus, pool: Pool,
                                 dataset: SceneDataset) -> None:
    resp = client.get("/render.png")
    assert resp.status_code == 404
    assert "no render yet" in resp.json()["detail"]
    pool.add("w1")
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(c, 0.0) for c in (1, 2)]))
    resp = wait_for(lambda: (r := client.get("/render.png")).status_code == 200 and r,
                    what="/render.png")
    assert resp.headers["content-type"] == "image/png"
    assert resp.headers["x-decision-id"] == "1" and resp.headers["x-worker"] == "w1"
    with Image.open(io.BytesIO(resp.content)) as img:
        assert img.size == (dataset.width, dataset.height)


def test_no_render_before_a_decision(client: TestClient, bus: MemoryBus, pool: Pool,
                                     dataset: SceneDataset) -> None:
    pool.add("w1")
    publish_frames(bus, dataset, 0.0)
    wait_for(lambda: client.get("/status").json()["frames_buffered"] == N_TRAIN,
             what="frames buffered")
    time.sleep(0.4)  # > one of the worker's waits
    status = client.get("/status").json()
    assert status["steps"] == 0 and status["decision"] is None and status["loss"] is None
    assert bus.messages(KEYS.render) == []
    ready = client.get("/readyz")
    assert ready.status_code == 200 and "first decision" in ready.json()["reason"]


def test_bad_messages_are_counted_and_dropped(client: TestClient, bus: MemoryBus, pool: Pool,
                                              dataset: SceneDataset) -> None:
    bus.publish(KEYS.edge_frame(1), b"\x0a\xff\xff garbage")
    bus.publish(KEYS.decision, b"\xff\xff\xff")
    bus.publish(KEYS.edge_frame(9), frame_payload(dataset, 1, 0.0)[:-10])  # truncated
    unknown = pb.Frame.FromString(frame_payload(dataset, 1, 0.0))
    unknown.camera_id = 99
    bus.publish(KEYS.edge_frame(99), unknown.SerializeToString())
    wrong_size = pb.Frame.FromString(frame_payload(dataset, 2, 0.0))
    wrong_size.intrinsics.width = 30
    bus.publish(KEYS.edge_frame(2), wrong_size.SerializeToString())
    bad_pose = pb.Frame.FromString(frame_payload(dataset, 3, 0.0))
    bad_pose.pose.c2w[0] = 2.0  # not a rotation any more
    bus.publish(KEYS.edge_frame(3), bad_pose.SerializeToString())
    # work requests that are not WorkRequests, or name no worker, get no answer
    assert bus.query(KEYS.work, b"\xff\xff", timeout_s=0.5) is None
    assert bus.query(KEYS.work, pb.WorkRequest(max_wait_s=1).SerializeToString(),
                     timeout_s=0.5) is None
    bad_render = pb.Render(decision_id=1, time_ms=math.nan)
    bus.publish(KEYS.render, bad_render.SerializeToString())

    def rejected(reason: str) -> float:
        return metric(client, "aoi3d_messages_rejected_total", f'reason="{reason}"', default=0.0)

    assert rejected("malformed") == 5  # frame, decision, truncated frame, two requests
    assert rejected("non_finite") == 1
    assert rejected("unknown_camera") == 1
    assert rejected("image_size_mismatch") == 1
    assert rejected("bad_pose") == 1
    assert client.get("/status").json()["frames_received"] == 0

    # the service is alive and the pool renders good input
    pool.add("w1")
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0), (2, 0.0)]))
    wait_for(lambda: renders(bus), what="a render after bad input")
    assert client.get("/readyz").status_code == 200


def test_put_backend_and_carry_change_the_jobs_and_refuse_bad_values(
        client: TestClient, bus: MemoryBus, pool: Pool, dataset: SceneDataset) -> None:
    resp = client.put("/backend", json={"backend": "nope"})
    assert resp.status_code == 422 and "available" in resp.json()["detail"]
    for body in ({"carry": "lukewarm"}, {"carry": "fresh", "render_steps": 0}):
        assert client.put("/carry", json=body).status_code == 422
    status = client.get("/status").json()
    assert (status["backend"], status["carry"], status["render_steps"]) == ("grid", "stream", 20)
    assert status["resets"] == 0

    resp = client.put("/backend", json={"backend": "ngp"})
    assert resp.status_code == 200 and resp.json()["backend"] == "ngp"
    resp = client.put("/carry", json={"carry": "warm"})
    assert resp.status_code == 200 and resp.json()["carry"] == "warm"
    assert resp.json()["render_steps"] == 20 and resp.json()["resets"] == 1
    assert client.post("/reset").json()["resets"] == 2

    pool.add("w1")
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0), (2, 0.0)]))
    wait_for(lambda: renders(bus), what="a warm ngp render")
    render = renders(bus)[-1]
    assert (render.backend, render.carry, render.render_steps) == ("ngp", "warm", 0)


def test_openapi_documents_the_routes(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    for path in ("/status", "/workers", "/reset", "/backend", "/carry", "/render.png",
                 "/healthz", "/readyz", "/metrics"):
        assert path in paths


def test_settings_validate_backend(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ValidationError, match="unknown field backend"):
        Settings(backend="nope")
    with pytest.raises(ValidationError):
        Settings(job_timeout_s=0)
    monkeypatch.setenv("AOI3D_DISPATCHER_JOB_TIMEOUT_S", "9")
    monkeypatch.setenv("AOI3D_CAMERAS", "5")
    s = Settings()
    assert (s.job_timeout_s, s.port, s.common.cameras) == (9.0, 8104, 5)


def test_the_default_is_the_stream_warm_start_of_25_steps(monkeypatch: pytest.MonkeyPatch
                                                         ) -> None:
    # what a viewer sees best live (docs/performance.md, "The live default")
    s = Settings()
    assert (s.carry, s.render_steps, s.cold_steps, s.warm_max_gap_ms) == ("stream", 25, 100,
                                                                           500.0)
    monkeypatch.setenv("AOI3D_DISPATCHER_CARRY", "fresh")
    monkeypatch.setenv("AOI3D_DISPATCHER_RENDER_STEPS", "100")
    assert (Settings().carry, Settings().render_steps) == ("fresh", 100)
    monkeypatch.setenv("AOI3D_DISPATCHER_CARRY", "lukewarm")
    with pytest.raises(ValidationError, match="carry"):
        Settings()


def test_by_default_a_workers_next_decision_starts_from_its_model(
        client: TestClient, bus: MemoryBus, pool: Pool, dataset: SceneDataset) -> None:
    pool.add("w1")
    wait_for(lambda: client.get("/workers").json()["workers"], what="the worker to join")
    publish_frames(bus, dataset, 0.0)
    publish_frames(bus, dataset, 100.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0), (2, 0.0)]))
    wait_for(lambda: len(renders(bus)) == 1, what="the first render")
    bus.publish(KEYS.decision, decision_payload(2, 200.0, [(1, 100.0), (2, 100.0)]))
    wait_for(lambda: len(renders(bus)) == 2, what="the second render")
    first, second = renders(bus)
    # a cold start first (cold_steps), then 100 scene ms later its model, render_steps more
    assert (first.carry, first.warm_start, first.render_steps) == ("stream", False, 20)
    assert (second.carry, second.warm_start, second.render_steps) == ("stream", True, 20)
    assert metric(client, "aoi3d_renders_warm_start_total", 'site="site1"') == 1


def test_recon_settings_default_to_one_thread_and_check_the_worker_id(
        monkeypatch: pytest.MonkeyPatch) -> None:
    assert ReconSettings().torch_threads == 1
    with pytest.raises(ValidationError):
        ReconSettings(worker_id="a/b")
    monkeypatch.setenv("AOI3D_RECON_DEVICE", "cuda")
    assert ReconSettings().device == "cuda"


def test_one_pool_serves_every_site_and_each_render_goes_to_its_site(
        dataset: SceneDataset, pool: Pool) -> None:
    bus = pool.bus
    settings = make_settings()
    settings.common.sites = ["north", "south"]
    clock = SimClock(settings.common.epoch_s, settings.common.time_scale)
    north, south = Keys(KEYS.run_id, "north"), Keys(KEYS.run_id, "south")
    with TestClient(create_app(settings, bus=bus, clock=clock, dataset=dataset)) as client:
        pool.add("w1")
        for keys in (north, south):
            for cam in range(1, N_TRAIN + 1):
                bus.publish(keys.edge_frame(cam), frame_payload(dataset, cam, 0.0))
        bus.publish(north.decision, decision_payload(5, 100.0, [(1, 0.0), (2, 0.0)]))
        bus.publish(south.decision, decision_payload(9, 100.0, [(3, 0.0)]))
        # a site that is not the run's is refused, whatever it sends
        bus.publish(Keys(KEYS.run_id, "east").decision, decision_payload(1, 100.0, []))
        wait_for(lambda: bus.messages(north.render) and bus.messages(south.render),
                 what="a render for each site")
        (n,), (s,) = ([pb.Render.FromString(p) for p in bus.messages(k.render)]
                      for k in (north, south))
        assert (n.decision_id, n.site, n.n_views) == (5, "north", 2)
        assert (s.decision_id, s.site, s.n_views) == (9, "south", 1)
        status = client.get("/sites/south/status").json()
        assert status["site"] == "south" and status["decision"]["decision_id"] == 9
        assert client.get("/status").json()["decision"]["decision_id"] == 5  # the first site
        assert client.get("/sites/south/render.png").headers["x-decision-id"] == "9"
        resp = client.get("/sites/east/status")
        assert resp.status_code == 404 and "north, south" in resp.json()["detail"]
        by_site = client.get("/workers").json()["by_site"]
        assert by_site["north"]["rendered"] == by_site["south"]["rendered"] == 1
        assert metric(client, "aoi3d_messages_rejected_total", 'reason="unknown_site"') == 1
        assert metric(client, "aoi3d_renders_total", 'site="south"') == 1


def test_the_old_trainer_names_are_read_for_one_release_and_named_in_a_warning(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The service was the trainer: AOI3D_TRAINER_* still works, the new name wins, and the
    start logs one deprecation line naming each old variable it read."""
    import importlib

    from services.dispatcher.settings import OLD_PREFIX
    from services.kit.renamed import renamed_variables

    monkeypatch.setenv("AOI3D_TRAINER_RENDER_STEPS", "7")
    monkeypatch.setenv("AOI3D_TRAINER_COLD_STEPS", "40")
    assert (Settings().render_steps, Settings().cold_steps) == (7, 40)
    monkeypatch.setenv("AOI3D_DISPATCHER_RENDER_STEPS", "9")
    assert Settings().render_steps == 9
    monkeypatch.setenv("AOI3D_TRAINER_SEED", "-1")  # refused as the new name would be
    with pytest.raises(ValidationError, match="seed"):
        Settings()
    monkeypatch.delenv("AOI3D_TRAINER_SEED")
    assert list(renamed_variables(OLD_PREFIX, "AOI3D_DISPATCHER_")) == [
        "AOI3D_TRAINER_COLD_STEPS", "AOI3D_TRAINER_RENDER_STEPS"]
    main = importlib.import_module("services.dispatcher.__main__")
    with caplog.at_level("WARNING"):
        main._warn_old_names(Settings())
    assert [r.getMessage() for r in caplog.records] == [
        "deprecated: AOI3D_TRAINER_COLD_STEPS, AOI3D_TRAINER_RENDER_STEPS read as "
        "AOI3D_DISPATCHER_COLD_STEPS, AOI3D_DISPATCHER_RENDER_STEPS; the old names go in the "
        "next release"]
