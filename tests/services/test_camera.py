"""The camera service: the dataset played back as a live rig on a fast clock."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client import generate_latest

from aoi3d.clock import SimClock
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset, load_dataset
from services.camera.app import create_app
from services.camera.settings import Settings
from services.kit.codec import FrameData, decode_frame
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.settings import CommonSettings
from tests.support.metrics import metric
from tests.support.timeouts import timeout_scale
from tests.support.waits import settle, wait_for

KEYS = Keys("t")
N_TRAIN = 3


@pytest.fixture(scope="module")
def dataset_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("scene") / "tiny"
    generate_dataset(path, SceneConfig(width=24, height=18, fps=10, duration_s=1.0,
                                       n_train=N_TRAIN, rotor_rpm=20.0, spp=1))
    return path


@pytest.fixture(scope="module")
def dataset(dataset_path: Path) -> SceneDataset:
    return load_dataset(dataset_path)


def make_app(bus: MemoryBus, clock: SimClock, path: Path, *, cameras: int = N_TRAIN,
             dataset: object | None = None, **overrides):
    settings = Settings(common=CommonSettings(run_id="t", cameras=cameras, dataset=path),
                        **overrides)
    return create_app(settings, bus=bus, clock=clock, dataset=dataset)




def frames(bus: MemoryBus, since: int = 0) -> list[tuple[str, FrameData]]:
    out = []
    for key, payload in bus.published[since:]:
        out.append((key, decode_frame(payload)))
    return out


TIMEOUT_SCALE = timeout_scale()




def test_frames_follow_the_dataset_on_the_tick_grid(dataset_path: Path,
                                                    dataset: SceneDataset) -> None:
    clock = SimClock(epoch_s=time.time(), time_scale=2.0)  # C = 30 sim ms = 15 ms wall
    bus = MemoryBus()
    arrivals: list[tuple[float, float]] = []

    def on_truth(key: str, payload: bytes) -> None:
        arrivals.append((time.time(), decode_frame(payload).generation_ms))

    bus.subscribe(KEYS.truth, on_truth)
    app = make_app(bus, clock, dataset_path)
    with TestClient(app) as client:
        wait_for(lambda: len(bus.messages(KEYS.truth)) >= 12)
        assert client.get("/readyz").json() == {"ready": True, "reason": ""}
    text = generate_latest(app.state.registry).decode()  # after stop: nothing in between
    got = frames(bus)
    by_camera: dict[int, list[FrameData]] = {}
    for key, f in got:
        expected_key = KEYS.truth if f.camera_id == 0 else KEYS.cam_frame(f.camera_id)
        assert key == expected_key
        by_camera.setdefault(f.camera_id, []).append(f)
        g = f.generation_ms
        assert g % 30 == 0 and f.sequence * 30 == g and f.send_ms == g
        assert f.delivery_ms == 0
        assert f.scene_time_ms == pytest.approx(dataset.scene_time_ms(g))
        assert f.image.data == dataset.frame_png(f.camera_id, dataset.frame_index(g))
        assert f.camera == dataset.cameras[f.camera_id]
    assert sorted(by_camera) == [0, 1, 2, 3]
    gens = [[f.generation_ms for f in by_camera[n]] for n in range(4)]
    assert all(g == gens[0] for g in gens[1:]), "every camera publishes at every tick"
    assert all(b > a for a, b in itertools.pairwise(gens[0]))
    assert len({dataset.frame_index(g) for g in gens[0]}) > 1, "the scene moves"
    for wall_s, g in arrivals:
        assert wall_s >= clock.wall_s(g) - 2e-3, "frame published before its time"
    for n in range(4):
        assert metric(text, "aoi3d_frames_generated_total", camera=str(n)) == len(by_camera[n])
    assert np.array_equal(by_camera[2][0].rgb(),
                          dataset.frame(2, dataset.frame_index(by_camera[2][0].generation_ms)))


def test_config_rest_api(dataset_path: Path) -> None:
    clock = SimClock(epoch_s=time.time(), time_scale=2.0)
    bus = MemoryBus()
    with TestClient(make_app(bus, clock, dataset_path)) as client:
        body = client.get("/config").json()
        assert body == {"period_ms": 30.0, "paused": False, "cameras": [1, 2, 3],
                        "rig": [1, 2, 3], "heldout_id": 0}

        for bad, needle in (({"cameras": [2, 4]}, "1..3"), ({"cameras": [0]}, "held-out"),
                            ({"period_ms": 0}, "greater than or equal to 1"),
                            ({"period_ms": "fast"}, "valid number"),
                            ({"period": 20}, "Extra inputs")):
            resp = client.put("/config", json=bad)
            assert resp.status_code == 422, bad
            assert needle in str(resp.json()["detail"]), resp.json()
        assert client.get("/config").json() == body

        resp = client.put("/config", json={"cameras": [2], "period_ms": 45})
        assert resp.status_code == 200
        assert resp.json() == body | {"cameras": [2], "period_ms": 45.0}
        time.sleep(0.05)  # a tick in progress may still use the old config
        mark = len(bus.published)
        wait_for(lambda: len(bus.published) - mark >= 10)
        recent = frames(bus, mark)
        assert {f.camera_id for _, f in recent} == {0, 2}
        assert all(f.generation_ms % 45 == 0 and f.sequence * 45 == f.generation_ms
                   for _, f in recent)

        assert client.put("/config", json={"paused": True}).json()["paused"] is True
        time.sleep(0.05)
        mark = len(bus.published)
        settle(0.3)  # several 45-ms ticks: a rig still running would publish
        assert len(bus.published) == mark, "paused rig still publishes"
        assert client.get("/readyz").json() == {"ready": True, "reason": "paused"}
        client.put("/config", json={"paused": False})
        wait_for(lambda: len(bus.published) > mark)


def test_falling_behind_skips_ticks_instead_of_bursting(dataset_path: Path) -> None:
    offset_s = [0.0]
    clock = SimClock(epoch_s=time.time(), time_scale=1.0,
                     wall=lambda: time.time() + offset_s[0])
    bus = MemoryBus()
    app = make_app(bus, clock, dataset_path)
    with TestClient(app):
        wait_for(lambda: len(bus.messages(KEYS.truth)) >= 2)
        offset_s[0] = 3.0  # the clock jumps 3000 sim ms = 100 ticks ahead
        n_before = len(bus.messages(KEYS.truth))
        wait_for(lambda: len(bus.messages(KEYS.truth)) >= n_before + 3)
    text = generate_latest(app.state.registry).decode()
    gens = [decode_frame(p).generation_ms for p in bus.messages(KEYS.truth)]
    skipped = metric(text, "aoi3d_camera_ticks_skipped_total")
    gaps = np.diff(gens) / 30
    assert gaps.max() >= 99, "one jump over the skipped ticks"
    assert np.sum(gaps - 1) == skipped, "every tick is either published or counted as skipped"
    assert skipped <= 105
    assert len(gens) == len(set(gens))


class _MissingCamera:
    """A dataset whose files of one camera are unreadable."""

    def __init__(self, inner: SceneDataset, missing: int) -> None:
        self._inner = inner
        self._missing = missing

    def __getattr__(self, name: str):
        return getattr(self._inner, name)

    def frame_png(self, cam: int, idx: int) -> bytes:
        if cam == self._missing:
            raise FileNotFoundError(f"frames/cam{cam:02d}/{idx:04d}.png")
        return self._inner.frame_png(cam, idx)


def test_an_unreadable_camera_does_not_stop_the_rig(dataset_path: Path,
                                                    dataset: SceneDataset) -> None:
    clock = SimClock(epoch_s=time.time(), time_scale=2.0)
    bus = MemoryBus()
    app = make_app(bus, clock, dataset_path, dataset=_MissingCamera(dataset, 2))
    with TestClient(app) as client:
        wait_for(lambda: len(bus.messages(KEYS.truth)) >= 5)
        assert client.get("/readyz").status_code == 200
    cams = {f.camera_id for _, f in frames(bus)}
    assert cams == {0, 1, 3}


def test_rig_larger_than_the_dataset_fails_at_startup(dataset_path: Path) -> None:
    app = make_app(MemoryBus(), SimClock(time.time(), 1.0), dataset_path, cameras=N_TRAIN + 2)
    with pytest.raises(ValueError, match=f"has {N_TRAIN}"), TestClient(app):
        pass


def test_settings_from_the_environment(monkeypatch: pytest.MonkeyPatch,
                                       dataset_path: Path) -> None:
    monkeypatch.setenv("AOI3D_CAMERA_ACTIVE_CAMERAS", "1,3")
    monkeypatch.setenv("AOI3D_CAMERA_PERIOD_MS", "60")
    monkeypatch.setenv("AOI3D_CAMERAS", str(N_TRAIN))
    monkeypatch.setenv("AOI3D_DATASET", str(dataset_path))
    settings = Settings()
    assert settings.port == 8101 and settings.active_cameras == [1, 3]
    clock = SimClock(epoch_s=time.time(), time_scale=0.1)
    client = TestClient(create_app(settings, bus=MemoryBus(), clock=clock))
    with client:
        assert client.get("/config").json()["cameras"] == [1, 3]
        assert client.get("/config").json()["period_ms"] == 60.0
        t0 = time.monotonic()
    assert time.monotonic() - t0 < 2.0, "stop must be prompt"
