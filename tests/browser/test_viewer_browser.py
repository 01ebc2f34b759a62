"""The 3D viewer in a real browser (Debian's Chromium driven by Playwright) against a real
pipeline on loopback (issue 42): the page loads from the viewer itself (no request leaves
127.0.0.1, no CDN), it draws a frustum per camera in the AoI colours of the decision in force,
and orbiting the viewer's camera changes the rendered view (the pool renders the new pose).
Its own free ports and scene; every wait is tests/support/waits.py's (through
tests/support/pipeline.py), scaled by AOI3D_TEST_TIMEOUT_SCALE, with budgets for a loaded 2-core
machine, and waits for what it checks (no fixed sleeps). The screenshot goes to the test's
folder (and to $AOI3D_VIEWER_SCREENSHOT if set: docs/figures/viewer.png is one)."""

from __future__ import annotations

import contextlib
import io
import os
import random
import shutil
import socket
import subprocess
import uuid
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

from aoi3d_cli.pipeline import Pipeline
from services.kit.ports import SERVICE_PORTS, PortBlock
from tests.support.pipeline import HTTP, SCALE, wait_for

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = [
    pytest.mark.integration, pytest.mark.slow,
    pytest.mark.skipif(not Path(CHROMIUM).is_file(),
                       reason="Debian's chromium not installed (.ci/setup/20-chromium.sh)"),
]
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed")

ARGS = ["--no-sandbox", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run", "--disable-quic", "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def _free(port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_block() -> tuple[int, int]:
    """(--port-offset, --zenoh-port) with every REST port and the Zenoh port free."""
    first, last = min(SERVICE_PORTS.values()), max(SERVICE_PORTS.values())
    for _ in range(200):
        base = random.randrange(20_000, 30_000)
        ports = [*range(base, base + last - first + 1), base + last - first + 1]
        if all(_free(p) for p in ports):
            return base - first, ports[-1]
    raise RuntimeError("no free block of ports")


def colour_pixels(png: bytes, colour: list[int], tol: int = 30) -> int:
    from PIL import Image

    with Image.open(io.BytesIO(png)) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.int16)
    return int((np.abs(rgb - np.asarray(colour)).max(axis=-1) <= tol).sum())


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from aoi3d.scene import SceneConfig, generate_dataset

    path = tmp_path_factory.mktemp("scene") / "turbine"
    generate_dataset(path, SceneConfig(width=48, height=36, duration_s=2.0, spp=2))
    return path


def test_the_viewer_in_a_browser(scene: Path, tmp_path: Path) -> None:
    offset, zenoh = free_block()
    pipe = Pipeline(PortBlock(offset, zenoh), timeout_s=30 * SCALE)
    url = pipe.url
    up = pipe.start(
        ["--dataset", str(scene), "--time-scale", "0.1", "--workers", "1"],
        run_id=f"view{uuid.uuid4().hex[:8]}", log_dir=tmp_path / "logs", output=subprocess.PIPE,
        env=dict(os.environ, AOI3D_DISPATCHER_RENDER_STEPS="30", AOI3D_SCHEDULER_POLICY="mat:70"))
    outside: list[str] = []
    try:
        for name in SERVICE_PORTS:
            wait_for(f"{name} /healthz",
                     lambda n=name: HTTP.get(url(n, "/healthz")).status_code == 200, 240)
        wait_for("a render", lambda: HTTP.get(url("dispatcher", "/render.png")).status_code == 200,
                 300)
        wait_for("a decision at the viewer",
                 lambda: HTTP.get(url("viewer", "/scene.json")).json()["decision"], 120)
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.set_default_timeout(60_000 * SCALE)
            page.on("request", lambda r: outside.append(r.url)
                    if urlsplit(r.url).hostname not in ("127.0.0.1", None)
                    and not r.url.startswith(("data:", "blob:")) else None)
            page.goto(url("viewer"))
            page.wait_for_selector("canvas")
            # software WebGL (no GPU here): viser says so in a notification; close it
            with contextlib.suppress(sync_api.Error):
                page.locator(".mantine-Notification-closeButton").first.click(timeout=5000 * SCALE)

            # the viewer asks the pool for its camera's view and shows it
            wait_for("a free view shown", lambda: HTTP.get(url("viewer", "/scene.json")).json()[
                "views"]["shown"] >= 1, 180)

            # a frustum per camera, in the AoI colours of the decision in force (drawn by the
            # viewer's loop, then by the browser: screenshots until they show)
            def drawn() -> tuple[dict, bytes] | None:
                doc = HTTP.get(url("viewer", "/scene.json")).json()
                png = page.screenshot()
                colours = {tuple(c["colour"]) for c in doc["cameras"] if c["aoi_ms"] is not None}
                shown = colours and all(colour_pixels(png, list(c)) >= 3 for c in colours)
                return (doc, png) if shown else None

            doc, first = wait_for("the frustums in the decision's AoI colours", drawn, 120,
                                  every_s=1.0)
            cameras = doc["cameras"]
            from aoi3d.scene import open_dataset

            ds = open_dataset(scene)
            assert [c["camera_id"] for c in cameras] == [
                i for i in range(1, min(18, len(ds.cameras) - 1) + 1) if i != ds.heldout_id]
            assert doc["decision"]["selected"] == sorted(
                c["camera_id"] for c in cameras if c["selected"])
            before_c2w = HTTP.get(url("viewer", "/scene.json")).json()["views"]["last"]["c2w"]

            # orbit: drag across the canvas; the pool renders the new pose, the view changes
            box = page.locator("canvas").first.bounding_box()
            assert box is not None
            x0, y0 = box["x"] + box["width"] * 0.45, box["y"] + box["height"] * 0.5
            page.mouse.move(x0, y0)
            page.mouse.down()
            for i in range(1, 11):
                page.mouse.move(x0 + 25 * i, y0 + 4 * i)
                page.wait_for_timeout(30)
            page.mouse.up()
            def moved() -> bool:
                last = HTTP.get(url("viewer", "/scene.json")).json()["views"]["last"]
                a = np.array(last["c2w"].split(","), float).reshape(4, 4)
                b = np.array(before_c2w.split(","), float).reshape(4, 4)
                return bool(np.linalg.norm(a[:3, 3] - b[:3, 3]) > 0.5)  # not a refresh

            wait_for("a free view of the new pose", moved, 120)
            from PIL import Image

            a = np.asarray(Image.open(io.BytesIO(first)).convert("RGB"), dtype=np.int16)

            def changed() -> bytes | None:
                png = page.screenshot()
                b = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
                return png if np.abs(a - b).mean() > 1.0 else None

            second = wait_for("the new view on screen", changed, 60, every_s=1.0)
            (tmp_path / "viewer.png").write_bytes(second)
            target = os.environ.get("AOI3D_VIEWER_SCREENSHOT")
            if target:
                Path(target).write_bytes(second)
            browser.close()
        trainer_metrics = HTTP.get(url("dispatcher", "/metrics")).text
        assert 'aoi3d_dispatcher_views_total{kind="view",outcome="served"}' in trainer_metrics
        assert not outside, outside
    finally:
        up.stop(60 * SCALE)
        up.close()
