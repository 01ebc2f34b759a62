"""The trainer service on a MemoryBus: real frames and decisions in, renders out."""

from __future__ import annotations

import io
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from pydantic import ValidationError

from aoi3d.clock import SimClock
from aoi3d.device import resolve_device
from aoi3d.field import FieldConfig, GridConfig
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from services.kit.bus import MemoryBus
from services.kit.codec import PNG, decode_image, decode_render, encode_frame
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.trainer.app import create_app
from services.trainer.settings import BACKENDS, Settings
from services.trainer.state import BackendBuildError, UnknownBackendError

N_TRAIN = 4
PERIOD_MS = 100.0  # one frame per period at fps = 10
KEYS = Keys("trainertest")
TIMEOUT_SCALE = float(os.environ.get("AOI3D_TEST_TIMEOUT_SCALE", "1"))
SMALL_GRID = GridConfig(batch_rays=128, samples_coarse=12, samples_fine=12, fine_from_step=0,
                        grid_sizes=(12,), upsample_steps=(), background_size=(4, 8),
                        render_chunk_rays=4096, tune_malloc=False)


@dataclass(frozen=True)
class TinyGrid(GridConfig):
    """A second backend for the switch tests (its defaults are small)."""

    batch_rays: int = 64
    samples_coarse: int = 8
    samples_fine: int = 8
    fine_from_step: int = 0
    grid_sizes: tuple[int, ...] = (6,)
    upsample_steps: tuple[int, ...] = ()
    background_size: tuple[int, int] = (4, 8)
    tune_malloc: bool = False


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=24, height=18, fps=10, duration_s=1.0, n_train=N_TRAIN,
                      rotor_rpm=20.0, spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", cfg, workers=1)


def make_settings(**overrides) -> Settings:
    common = CommonSettings(run_id=KEYS.run_id, cameras=N_TRAIN, time_scale=10.0,
                            epoch_s=time.time())
    values = {"render_period_s": 0.15, "steps_per_chunk": 2, "device": "cpu", "common": common,
              "checkpoint_period_s": 0}  # the checkpoint tests turn them on
    values.update(overrides)
    return Settings(**values)


@pytest.fixture
def bus() -> MemoryBus:
    return MemoryBus()


@pytest.fixture
def client(dataset: SceneDataset, bus: MemoryBus) -> Iterator[TestClient]:
    settings = make_settings()
    clock = SimClock(settings.common.epoch_s, settings.common.time_scale)
    app = create_app(settings, bus=bus, clock=clock, dataset=dataset, field_config=SMALL_GRID)
    with TestClient(app) as c:
        yield c


# ------------------------------------------------------------------------ helpers
def frame_payload(ds: SceneDataset, camera_id: int, generation_ms: float) -> bytes:
    idx = ds.frame_index(generation_ms)
    image = pb.Image(encoding=PNG, width=ds.width, height=ds.height,
                     data=ds.frame_png(camera_id, idx))
    return encode_frame(camera_id=camera_id, sequence=int(generation_ms // PERIOD_MS),
                        generation_ms=generation_ms, scene_time_ms=ds.scene_time_ms(generation_ms),
                        camera=ds.cameras[camera_id], image=image, send_ms=generation_ms,
                        delivery_ms=generation_ms + 40.0)


def publish_frames(bus: MemoryBus, ds: SceneDataset, generation_ms: float) -> None:
    for cam in range(1, N_TRAIN + 1):
        bus.publish(KEYS.edge_frame(cam), frame_payload(ds, cam, generation_ms))


def decision_payload(decision_id: int, time_ms: float, refs: list[tuple[int, float]],
                     policy: str = "all") -> bytes:
    ids = list(range(1, N_TRAIN + 1))
    selected = [pb.FrameRef(camera_id=c, sequence=int(g // PERIOD_MS), generation_ms=g,
                            aoi_ms=time_ms - g) for c, g in refs]
    return pb.Decision(decision_id=decision_id, time_ms=time_ms, camera_ids=ids,
                       aoi_ms=[50.0] * len(ids), selected=selected,
                       policy=policy).SerializeToString()


def wait_for(predicate: Callable[[], object], timeout_s: float = 10.0, what: str = "") -> object:
    deadline = time.monotonic() + timeout_s * TIMEOUT_SCALE
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what or predicate}")


def metric(client: TestClient, name: str, labels: str = "",
           default: float | None = None) -> float:
    """A series' value from /metrics; ``default`` if it is not exported (else an error)."""
    series = f"{name}{{{labels}}}" if labels else name
    for line in client.get("/metrics").text.splitlines():
        if line.startswith(series + " "):
            return float(line.split()[-1])
    if default is not None:
        return default
    raise AssertionError(f"series {series} not exported")


def renders(bus: MemoryBus) -> list[pb.Render]:
    return [decode_render(p)[0] for p in bus.messages(KEYS.render)]


# ------------------------------------------------------------------------ tests
def test_trains_on_the_decision_and_publishes_renders(client: TestClient, bus: MemoryBus,
                                                       dataset: SceneDataset) -> None:
    # the continuously trained model, rendered as it is (the fresh default: further below)
    assert client.put("/carry", json={"carry": "warm"}).status_code == 200
    publish_frames(bus, dataset, 0.0)
    publish_frames(bus, dataset, 100.0)
    # Cameras 1-3 at 100 ms are delivered; camera 4's frame at 900 ms never was.
    refs = [(1, 100.0), (2, 100.0), (3, 100.0), (4, 900.0)]
    bus.publish(KEYS.decision, decision_payload(7, 200.0, refs, policy="mat:51"))

    status = wait_for(lambda: (s := client.get("/status").json())["steps"] >= 6 and s,
                      what="training steps")
    assert status["n_views"] == 3
    assert status["frames_missing"] == 1
    assert status["decision"]["decision_id"] == 7
    assert status["decision"]["time_ms"] == 200.0
    assert status["decision"]["policy"] == "mat:51"
    assert status["decision"]["n_missing"] == 1
    assert status["backend"] == "grid" and status["backends"] == sorted(BACKENDS)
    assert status["device"] == "cpu"
    assert status["frames_buffered"] == status["frames_received"] == 2 * N_TRAIN
    assert math.isfinite(status["loss"]) and status["loss"] > 0
    assert status["steps_per_s"] > 0

    wait_for(lambda: renders(bus), what="a render")
    render, camera = decode_render(bus.messages(KEYS.render)[-1])
    assert (render.decision_id, render.time_ms) == (7, 200.0)
    assert render.backend == "grid" and render.n_views == 3 and render.training_step > 0
    assert camera == dataset.cameras[dataset.heldout_id]
    rgb = decode_image(render.image)
    assert rgb.shape == (dataset.height, dataset.width, 3) and rgb.dtype == np.uint8

    assert metric(client, "aoi3d_trainer_steps_total") >= 6
    assert metric(client, "aoi3d_trainer_views") == 3
    assert metric(client, "aoi3d_trainer_frames_received_total") == 2 * N_TRAIN
    assert metric(client, "aoi3d_trainer_frames_missing_total") == 1
    assert metric(client, "aoi3d_renders_total") >= 1
    assert math.isfinite(metric(client, "aoi3d_trainer_loss"))
    assert metric(client, "aoi3d_trainer_steps_per_second") > 0

    # A newer decision takes over within a chunk; the model is kept (steps keep growing).
    steps_before = client.get("/status").json()["steps"]
    publish_frames(bus, dataset, 200.0)
    bus.publish(KEYS.decision, decision_payload(8, 300.0, [(1, 200.0), (2, 200.0)]))
    status = wait_for(lambda: (s := client.get("/status").json())["decision"]["decision_id"] == 8
                      and s, what="decision 8")
    assert status["n_views"] == 2 and status["steps"] >= steps_before
    wait_for(lambda: any(r.decision_id == 8 and r.time_ms == 300.0 for r in renders(bus)),
             what="a render of decision 8")

    # An older or repeated decision is rejected, not applied.
    bus.publish(KEYS.decision, decision_payload(8, 300.0, [(1, 200.0)]))
    wait_for(lambda: metric(client, "aoi3d_messages_rejected_total", 'reason="stale_decision"',
                            default=0.0), what="stale decision counted")
    assert client.get("/status").json()["n_views"] == 2


def test_render_png_404_then_200(client: TestClient, bus: MemoryBus,
                                 dataset: SceneDataset) -> None:
    resp = client.get("/render.png")
    assert resp.status_code == 404
    assert "no render yet" in resp.json()["detail"]

    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(c, 0.0) for c in (1, 2)]))
    resp = wait_for(lambda: (r := client.get("/render.png")).status_code == 200 and r,
                    what="/render.png")
    assert resp.headers["content-type"] == "image/png"
    assert resp.headers["x-decision-id"] == "1"
    with Image.open(io.BytesIO(resp.content)) as img:
        assert img.size == (dataset.width, dataset.height)


def test_no_render_and_no_training_before_a_decision(client: TestClient, bus: MemoryBus,
                                                     dataset: SceneDataset) -> None:
    publish_frames(bus, dataset, 0.0)
    wait_for(lambda: client.get("/status").json()["frames_buffered"] == N_TRAIN,
             what="frames buffered")
    time.sleep(0.4)  # > 2 render periods
    status = client.get("/status").json()
    assert status["steps"] == 0 and status["decision"] is None and status["loss"] is None
    assert bus.messages(KEYS.render) == []
    ready = client.get("/readyz")
    assert ready.status_code == 200 and "first decision" in ready.json()["reason"]


def test_bad_messages_are_counted_and_dropped(client: TestClient, bus: MemoryBus,
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

    def rejected(reason: str) -> float:
        return metric(client, "aoi3d_messages_rejected_total", f'reason="{reason}"', default=0.0)

    wait_for(lambda: rejected("malformed") >= 3, what="malformed counted")
    assert rejected("unknown_camera") == 1
    assert rejected("image_size_mismatch") == 1
    assert rejected("bad_pose") == 1
    assert client.get("/status").json()["frames_received"] == 0

    # The worker is still alive and trains on good input.
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0), (2, 0.0)]))
    status = wait_for(lambda: (s := client.get("/status").json())["steps"] > 0 and s,
                      what="training after bad input")
    assert status["running"] and status["n_views"] == 2
    assert client.get("/readyz").status_code == 200


def test_reset_keeps_views_and_restarts_the_model(client: TestClient, bus: MemoryBus,
                                                  dataset: SceneDataset) -> None:
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(c, 0.0) for c in (1, 2, 3)]))
    before = wait_for(lambda: (s := client.get("/status").json())["steps"] >= 40 and s,
                      what="40 steps")
    resp = client.post("/reset")
    assert resp.status_code == 200
    after = resp.json()
    assert after["resets"] == 1 and after["n_views"] == 3
    assert after["steps"] < before["steps"]
    assert after["steps_total"] >= before["steps_total"]
    assert after["frames_buffered"] == N_TRAIN
    wait_for(lambda: client.get("/status").json()["steps"] > after["steps"],
             what="training resumes after reset")
    assert metric(client, "aoi3d_trainer_steps_total") >= before["steps_total"]


def test_put_backend_switches_the_model_and_keeps_the_views(
        client: TestClient, bus: MemoryBus, dataset: SceneDataset,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(BACKENDS, "tiny", TinyGrid)
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(c, 0.0) for c in (1, 2, 3)]))
    before = wait_for(lambda: (s := client.get("/status").json())["steps"] >= 40 and s,
                      what="40 steps")
    assert before["backend"] == "grid" and "tiny" in before["backends"]

    resp = client.put("/backend", json={"backend": "tiny"})
    assert resp.status_code == 200, resp.text
    after = resp.json()
    assert after["backend"] == "tiny" and after["resets"] == 1
    assert after["steps"] < before["steps"] and after["steps_total"] >= before["steps_total"]
    assert after["n_views"] == 3 and after["frames_buffered"] == N_TRAIN
    assert after["decision"]["decision_id"] == 1
    worker = client.app.state.worker
    assert type(worker.trainer.cfg) is TinyGrid and worker.trainer.n_views == 3
    wait_for(lambda: client.get("/status").json()["steps"] > after["steps"],
             what="training resumes on the new backend")
    wait_for(lambda: any(r.backend == "tiny" for r in renders(bus)), what="a render by tiny")

    # Back to grid: the config the app was built with is used again, not grid's defaults.
    resp = client.put("/backend", json={"backend": "grid"})
    assert resp.status_code == 200 and resp.json()["backend"] == "grid"
    assert resp.json()["resets"] == 2 and worker.trainer.cfg == SMALL_GRID

    # Unknown names and bad bodies are refused; the model is left alone.
    resp = client.put("/backend", json={"backend": "instant-nerf"})
    assert resp.status_code == 422
    assert resp.json()["detail"] == ("unknown backend 'instant-nerf'; available: "
                                     + ", ".join(sorted(BACKENDS)))
    assert client.put("/backend", json={"name": "grid"}).status_code == 422
    status = client.get("/status").json()
    assert status["backend"] == "grid" and status["resets"] == 2


def test_a_backend_that_cannot_be_built_keeps_the_old_one(
        client: TestClient, bus: MemoryBus, dataset: SceneDataset,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(BACKENDS, "broken", FieldConfig)  # FieldConfig builds no field
    publish_frames(bus, dataset, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0), (2, 0.0)]))
    wait_for(lambda: client.get("/status").json()["steps"] > 0, what="training")
    resp = client.put("/backend", json={"backend": "broken"})
    assert resp.status_code == 500
    assert "could not build backend 'broken'" in resp.json()["detail"]
    assert "still training 'grid'" in resp.json()["detail"]
    steps = client.get("/status").json()["steps_total"]
    status = wait_for(lambda: (s := client.get("/status").json())["steps_total"] > steps and s,
                      what="grid trains on")
    assert status["backend"] == "grid" and status["resets"] == 0 and status["running"]


def test_set_backend_without_the_training_thread(dataset: SceneDataset,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from prometheus_client import CollectorRegistry

    from services.trainer.worker import TrainerWorker

    monkeypatch.setitem(BACKENDS, "tiny", TinyGrid)
    monkeypatch.setitem(BACKENDS, "broken", FieldConfig)
    settings = make_settings(torch_threads=1)
    worker = TrainerWorker(settings, MemoryBus(), CollectorRegistry(), dataset=dataset,
                           clock=SimClock(0.0, 1.0), field_config=SMALL_GRID)
    listing = r"available: (.*, )?broken, (.*, )?grid, (.*, )?tiny"
    with pytest.raises(UnknownBackendError, match=listing):
        worker.set_backend("nope")
    assert worker.set_backend("tiny") is True
    assert worker.status().backend == "tiny"
    assert worker.trainer.cfg == TinyGrid(num_threads=1)  # the service's threads apply
    with pytest.raises(BackendBuildError, match="still training 'tiny'"):
        worker.set_backend("broken")
    assert worker.status().backend == "tiny" and worker.status().resets == 1


def test_app_stops_promptly(dataset: SceneDataset) -> None:
    bus = MemoryBus()
    app = create_app(make_settings(), bus=bus, dataset=dataset, field_config=SMALL_GRID)
    with TestClient(app) as c:
        publish_frames(bus, dataset, 0.0)
        bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0)]))
        wait_for(lambda: c.get("/status").json()["steps"] > 0, what="training")
        worker = app.state.worker
        t0 = time.monotonic()
    assert time.monotonic() - t0 < 2.0
    assert not worker.status().running
    assert not bus.closed  # an injected bus belongs to the caller


def test_openapi_documents_the_routes(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/status", "/reset", "/backend", "/render.png", "/metrics", "/readyz"} <= set(paths)
    assert "post" in paths["/reset"]
    put = paths["/backend"]["put"]
    assert {"200", "422", "500", "503"} <= set(put["responses"])
    assert "views" in put["summary"] and "buffered frames are kept" in put["description"]


def test_settings_validate_backend_and_device(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ValidationError, match="available: " + ", ".join(sorted(BACKENDS))):
        Settings(backend="no-such-backend")
    assert Settings().backend == "grid" and "grid" in BACKENDS
    with pytest.raises(ValidationError):
        Settings(device="tpu")
    with pytest.raises(ValidationError):
        Settings(steps_per_chunk=0)
    monkeypatch.setenv("AOI3D_TRAINER_STEPS_PER_CHUNK", "9")
    monkeypatch.setenv("AOI3D_TRAINER_RENDER_PERIOD_S", "0.5")
    monkeypatch.setenv("AOI3D_CAMERAS", "5")
    s = Settings()
    assert (s.steps_per_chunk, s.render_period_s, s.port, s.common.cameras) == (9, 0.5, 8104, 5)
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") in ("cpu", "cuda")
    with pytest.raises(ValueError, match="accepted: auto, cpu, cuda"):
        resolve_device("tpu")


def test_cuda_request_without_cuda_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="CUDA is not available"):
        resolve_device("cuda")
    assert resolve_device("auto") == "cpu"


def test_inbox_overflow_is_counted(dataset: SceneDataset) -> None:
    from prometheus_client import CollectorRegistry

    from services.trainer.worker import TrainerWorker

    registry = CollectorRegistry()
    settings = make_settings()
    worker = TrainerWorker(settings, MemoryBus(), registry, dataset=dataset,
                           clock=SimClock(settings.common.epoch_s, 1.0), field_config=SMALL_GRID)
    payload = frame_payload(dataset, 1, 0.0)
    for _ in range(300):  # the thread is not started: nothing drains the 256-frame inbox
        worker._on_frame(KEYS.edge_frame(1), payload)
    worker._ingest()
    assert registry.get_sample_value("aoi3d_trainer_inbox_overflow_total") == 300 - 256
    assert registry.get_sample_value("aoi3d_trainer_frames_received_total") == 256
    assert worker.status().frames_buffered == settings.frames_per_camera


def test_torch_threads_go_into_the_field_config(dataset: SceneDataset) -> None:
    import torch
    from prometheus_client import CollectorRegistry

    from services.trainer.worker import TrainerWorker

    before = torch.get_num_threads()
    other = 1 if before != 1 else 2
    try:
        settings = make_settings(torch_threads=other)
        worker = TrainerWorker(settings, MemoryBus(), CollectorRegistry(), dataset=dataset,
                               clock=SimClock(0.0, 1.0), field_config=SMALL_GRID)
        assert worker.trainer.cfg.num_threads == other
        # the process-wide setting is the entry point's (services/trainer/__main__.py)
        assert torch.get_num_threads() == before
    finally:
        torch.set_num_threads(before)


def test_renders_carry_their_decision_frames_and_the_carry(client: TestClient, bus: MemoryBus,
                                                           dataset: SceneDataset) -> None:
    status = client.get("/status").json()
    assert (status["carry"], status["render_steps"]) == ("fresh", 100)
    resp = client.put("/carry", json={"carry": "fresh", "render_steps": 5})
    assert resp.status_code == 200 and resp.json()["render_steps"] == 5
    publish_frames(bus, dataset, 0.0)
    publish_frames(bus, dataset, 100.0)
    bus.publish(KEYS.decision, decision_payload(3, 160.0, [(1, 100.0), (2, 0.0)]))
    render = wait_for(lambda: next((r for r in renders(bus) if r.decision_id == 3), None),
                      what="a render of decision 3")
    assert render.carry == "fresh" and render.render_steps == 5
    assert render.training_step == 5 and render.n_views == 2  # a new model, its 5 steps
    assert sorted(render.frame_generation_ms) == [0.0, 100.0]
    assert metric(client, "aoi3d_render_frames_age_seconds") == pytest.approx(0.11)
    assert metric(client, "aoi3d_render_steps") == 5
    assert metric(client, "aoi3d_render_age_seconds") >= 0
    png = client.get("/render.png")
    assert png.headers["x-carry"] == "fresh" and png.headers["x-render-steps"] == "5"
    assert float(png.headers["x-frames-age-ms"]) == pytest.approx(110.0)

    # warm: the continuously trained model renders as it is; fork: a copy trains 4 steps
    assert client.put("/carry", json={"carry": "warm"}).json()["carry"] == "warm"
    wait_for(lambda: any(r.carry == "warm" and r.render_steps == 0 for r in renders(bus)),
             what="a warm render")
    assert client.put("/carry", json={"carry": "fork", "render_steps": 4}).status_code == 200
    fork = wait_for(lambda: next((r for r in renders(bus) if r.carry == "fork"), None),
                    what="a fork render")
    assert fork.render_steps == 4 and fork.training_step >= 4


def test_put_carry_refuses_bad_settings_and_changes_nothing(client: TestClient) -> None:
    for body in ({"carry": "cold"}, {"carry": "fork", "render_steps": 0}, {},
                 {"carry": "fresh", "render_steps": 1.5}):
        resp = client.put("/carry", json=body)
        assert resp.status_code == 422, body
    status = client.get("/status").json()
    assert (status["carry"], status["render_steps"]) == ("fresh", 100)
