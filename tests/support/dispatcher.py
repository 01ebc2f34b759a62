"""The dispatcher's tests' scene, settings and messages (tests/services/test_dispatcher.py,
the guard, the poison tests, the API fuzz and the dispatcher core): a 24×18 scene of 4 cameras
at 10 fps, frames and decisions of it."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from aoi3d.field import FlowConfig, GridConfig, NgpConfig
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from services.dispatcher.settings import Settings
from services.kit.codec import PNG, encode_frame
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from tests.support.metrics import REQUIRED, value

N_TRAIN = 4
PERIOD_MS = 100.0  # one frame per period at fps = 10
KEYS = Keys("trainertest")
SMALL_GRID = GridConfig(batch_rays=128, samples_coarse=12, samples_fine=12, fine_from_step=0,
                        grid_sizes=(12,), upsample_steps=(), background_size=(4, 8),
                        render_chunk_rays=4096, tune_malloc=False)
TINY_NGP = NgpConfig(batch_rays=64, samples_coarse=8, samples_fine=8, fine_from_step=0,
                     n_levels=2, features=2, log2_table_size=8, base_resolution=4,
                     max_resolution=16, hidden=8, geo_features=3, background_size=(4, 8),
                     occupancy_size=8, tune_malloc=False)
SMALL_FLOW = FlowConfig(batch_rays=128, samples_coarse=12, samples_fine=12, fine_from_step=0,
                        grid_sizes=(12,), upsample_steps=(), background_size=(4, 8),
                        render_chunk_rays=4096, tune_malloc=False, flow_size=4, lr_flow=0.1)
CONFIGS = {"grid": SMALL_GRID, "ngp": TINY_NGP, "flow": SMALL_FLOW}


def trainer_scene(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    """The dispatcher tests' scene, generated in a fresh temporary folder (the ``dataset``
    fixture of tests/services/conftest.py, and tests/unit/cores/test_dispatcher_core.py's)."""
    cfg = SceneConfig(width=24, height=18, fps=10, duration_s=1.0, n_train=N_TRAIN,
                      rotor_rpm=20.0, spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", cfg, processes=1)


def make_settings(**overrides) -> Settings:
    common = CommonSettings(run_id=KEYS.run_id, cameras=N_TRAIN, time_scale=10.0,
                            epoch_s=time.time())
    # the default carry (stream) with every job 20 steps: a cold start as cheap as a warm one
    values = {"render_steps": 20, "cold_steps": 20, "common": common}
    values.update(overrides)
    return Settings(**values)


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
                     policy: str = "all", *, budget_steps: int | None = None) -> bytes:
    """A Decision selecting ``refs`` (camera, generation ms); ``budget_steps``: its budget
    (absent: the pool's render_steps)."""
    ids = list(range(1, N_TRAIN + 1))
    selected = [pb.FrameRef(camera_id=c, sequence=int(g // PERIOD_MS), generation_ms=g,
                            aoi_ms=time_ms - g) for c, g in refs]
    msg = pb.Decision(decision_id=decision_id, time_ms=time_ms, camera_ids=ids,
                      aoi_ms=[50.0] * len(ids), selected=selected, policy=policy)
    if budget_steps is not None:
        msg.budget_steps = budget_steps
    return msg.SerializeToString()


def metric(client: TestClient, name: str, labels: str = "",
           default: float | None = None) -> float:
    """A series' value from the dispatcher's /metrics (``labels``: as exposed, ``'a="1"'``);
    ``default`` if it is not exported (else an error)."""
    series = f"{name}{{{labels}}}" if labels else name
    got = value(client.get("/metrics").text, series,
                REQUIRED if default is None else default)
    assert got is not None
    return got
