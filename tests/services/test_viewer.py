"""The 3D viewer service on a MemoryBus: its page is viser's client served from the wheel
(nothing from outside), its websocket is relayed to viser, and what it draws follows the
decision in force (AoI colours, the cameras used); a browser's camera becomes the dispatcher's
free-view query, and the status line says what is shown. Waits: tests/support/waits.py."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from types import SimpleNamespace

import pytest
from fastapi.testclient import TestClient

from aoi3d.freeview import MAX_VIEW_SIDE, aoi_colour, c2w_from_viser
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.viewer.app import create_app
from services.viewer.core import box_segments
from services.viewer.drawing import status_text, view_params
from services.viewer.settings import Settings
from tests.support.waits import wait_for

N = 4
KEYS = Keys("viewertest")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=24, height=18, fps=10, duration_s=0.4, n_train=N, rotor_rpm=0.0,
                      spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "s", cfg, processes=1)


@pytest.fixture
def viewer(dataset: SceneDataset) -> Iterator[tuple[TestClient, MemoryBus]]:
    bus = MemoryBus()
    settings = Settings(common=CommonSettings(run_id=KEYS.run_id, cameras=N))
    with TestClient(create_app(settings, bus=bus, dataset=dataset),
                    base_url="http://127.0.0.1") as client:
        yield client, bus


def test_the_page_is_vipers_client_and_loads_nothing_from_outside(viewer) -> None:
    client, _ = viewer
    r = client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    html = r.text
    assert '<div id="root">' in html
    urls = re.findall(r'(?:src|href)\s*=\s*["\']([^"\']+)["\']', html)
    assert all(u.startswith(("data:", "/", "#")) for u in urls), urls
    assert client.get("/healthz").json()["status"] == "ok"
    assert client.get("/readyz").json()["ready"] is True


def test_the_websocket_is_relayed_to_viser(viewer) -> None:
    import viser

    client, _ = viewer
    with client.websocket_connect("ws://127.0.0.1/",
                                  subprotocols=[f"viser-v{viser.__version__}"]) as ws:
        assert len(ws.receive_bytes()) > 0  # viser's first scene messages
    with pytest.raises(Exception), client.websocket_connect(  # noqa: B017
            "ws://127.0.0.1/", headers={"origin": "http://evil.example"}) as ws:
        ws.receive_bytes()


def test_what_is_drawn_follows_the_decision_in_force(viewer) -> None:
    client, bus = viewer
    doc = client.get("/scene.json").json()
    assert [c["camera_id"] for c in doc["cameras"]] == list(range(1, N + 1))
    assert all(c["colour"] == [128, 128, 128] and not c["selected"] for c in doc["cameras"])
    aoi = [10.0, 90.0, 180.0, 400.0]
    bus.publish(KEYS.decision, pb.Decision(
        decision_id=3, time_ms=500.0, camera_ids=list(range(1, N + 1)), aoi_ms=aoi,
        selected=[pb.FrameRef(camera_id=1, sequence=4, generation_ms=490.0, aoi_ms=10.0),
                  pb.FrameRef(camera_id=2, sequence=4, generation_ms=410.0, aoi_ms=90.0)],
        policy="mat", gamma_ms=100.0).SerializeToString())
    doc = wait_for(lambda: (d := client.get("/scene.json").json())["decision"] and d, 30.0,
                   what="the decision at the viewer", every_s=0.05)
    assert doc["decision"]["selected"] == [1, 2] and doc["decision"]["gamma_ms"] == 100.0
    for cam, a in zip(doc["cameras"], aoi, strict=True):
        assert cam["colour"] == list(aoi_colour(a, 100.0))
        assert cam["selected"] == (cam["camera_id"] in (1, 2))
    assert len({tuple(c["colour"]) for c in doc["cameras"]}) == N
    assert client.get("/scene.json", params={"site": "nosuch"}).status_code == 404


def test_box_has_twelve_edges_along_the_axes() -> None:
    seg = box_segments([[0, 0, 0], [1, 2, 3]])
    assert seg.shape == (12, 2, 3)
    assert all((abs(s[1] - s[0]) > 0).sum() == 1 for s in seg)


def test_a_browsers_camera_becomes_the_trainers_free_view_query() -> None:
    cam = SimpleNamespace(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.5, -4.0, 1.5), aspect=2.0,
                          fov=math.radians(60.0))
    p = view_params(cam, 120)
    assert p is not None and (p["width"], p["height"]) == (240, 120)
    assert p["fov"] == pytest.approx(60.0)
    c2w = [float(v) for v in str(p["c2w"]).split(",")]
    assert c2w == pytest.approx(c2w_from_viser(cam.wxyz, cam.position).ravel().tolist())
    assert view_params(SimpleNamespace(**{**vars(cam), "aspect": math.nan}), 120)["width"] == 160
    assert view_params(SimpleNamespace(**{**vars(cam), "aspect": 50.0}), 120)["width"] == (
        MAX_VIEW_SIDE)
    assert view_params(SimpleNamespace(**{**vars(cam), "fov": 3.14}), 120)["fov"] == 179.0
    assert view_params(SimpleNamespace(**{**vars(cam), "wxyz": None}), 120) is None  # unknown


def test_the_status_line_names_the_decision_and_the_model_shown() -> None:
    doc = {"site": "site1", "decision": None, "cameras": [{}] * 3}
    assert status_text(doc, {}) == "**site1**: waiting for the first decision"
    doc["decision"] = {"decision_id": 7, "policy": "mat", "gamma_ms": 70.0, "selected": [1, 3]}
    text = status_text(doc, {"decision_id": "6", "training_step": "30", "worker": "w1"})
    assert text.startswith("**site1** decision 7 (mat, Γ 70 ms): 2 of 3 cameras used")
    assert text.endswith("view: decision 6, step 30, worker w1")



class _Browser:
    """What the worker touches of a viser client when one connects (its camera and an atomic
    block): the real ones need viser's browser client (tests/browser drives one)."""

    def __init__(self, client_id: int) -> None:
        self.client_id = client_id
        self.camera = SimpleNamespace(on_update=lambda fn: fn)

    def atomic(self):
        import contextlib

        return contextlib.nullcontext()


def test_delivered_frames_are_kept_only_while_a_browser_is_connected(viewer) -> None:
    """The thumbnails' frames (600 a second at the default rig) are subscribed at the first
    browser and undeclared when the last one leaves."""
    from tests.support.network import frame

    client, bus = viewer
    worker = client.app.state.worker
    site = worker.core.sites[worker.site]
    bus.publish(KEYS.edge_frame(1), frame(1, 100.0))
    assert 1 not in site.frames  # nobody watching: not even received
    first, second = _Browser(1), _Browser(2)
    worker._on_client(first)
    worker._on_client(second)
    bus.publish(KEYS.edge_frame(1), frame(1, 200.0))
    assert site.frame_ms.get(1) == 200.0
    worker._on_client_gone(first)  # one still watches
    bus.publish(KEYS.edge_frame(1), frame(1, 300.0))
    assert site.frame_ms[1] == 300.0
    worker._on_client_gone(second)
    bus.publish(KEYS.edge_frame(1), frame(1, 400.0))
    assert site.frame_ms[1] == 300.0


def test_the_old_dispatcher_url_name_is_read_and_named_in_one_deprecation_line(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    import importlib

    monkeypatch.delenv("AOI3D_VIEWER_DISPATCHER_URL", raising=False)
    monkeypatch.setenv("AOI3D_VIEWER_TRAINER_URL", "http://edge:9104")
    assert Settings().dispatcher_url == "http://edge:9104"
    main = importlib.import_module("services.viewer.__main__")
    with caplog.at_level("WARNING"):
        main._warn_old_names(Settings())
    assert [r.getMessage() for r in caplog.records] == [
        "deprecated: AOI3D_VIEWER_TRAINER_URL read as AOI3D_VIEWER_DISPATCHER_URL; the old "
        "names go in the next release"]
    monkeypatch.setenv("AOI3D_VIEWER_DISPATCHER_URL", "http://new:8104")  # the new name wins
    assert Settings().dispatcher_url == "http://new:8104"
    caplog.clear()
    monkeypatch.delenv("AOI3D_VIEWER_TRAINER_URL")
    main._warn_old_names(Settings())
    assert not caplog.records
