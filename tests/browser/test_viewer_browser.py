"""The 3D viewer in a real browser (Debian's Chromium driven by Playwright) against a real
pipeline on loopback (issue 42): the page loads from the viewer itself (no request leaves
127.0.0.1, no CDN), it draws a frustum per camera in the AoI colours of the decision in force,
and orbiting the viewer's camera changes the rendered view (the pool renders the new pose).
Self-contained: its own free ports, its own scene; every wait scales with
AOI3D_TEST_TIMEOUT_SCALE. The screenshot goes to the test's folder (and to
$AOI3D_VIEWER_SCREENSHOT if set: docs/figures/viewer.png is one)."""

from __future__ import annotations

import contextlib
import io
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest

from aoi3d.ports import SERVICE_PORTS
from tests.support.timeouts import timeout_scale

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = [
    pytest.mark.integration, pytest.mark.slow,
    pytest.mark.skipif(not Path(CHROMIUM).is_file(),
                       reason="Debian's chromium not installed (.ci/setup/20-chromium.sh)"),
]
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed")

SCALE = timeout_scale()
ARGS = ["--no-sandbox", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run", "--disable-quic", "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
HTTP = httpx.Client(timeout=10.0)


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


def wait_for(what: str, check: Callable[[], object], timeout_s: float) -> object:
    deadline = time.monotonic() + timeout_s * SCALE
    while time.monotonic() < deadline:
        try:
            value = check()
        except httpx.HTTPError:
            value = None
        if value:
            return value
        time.sleep(0.25)
    raise AssertionError(f"timed out waiting for {what}")


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

    def url(service: str, path: str = "/") -> str:
        return f"http://127.0.0.1:{SERVICE_PORTS[service] + offset}{path}"

    up = subprocess.Popen(
        [sys.executable, "-m", "aoi3d_cli", "up", "--dataset", str(scene), "--run-id",
         f"view{uuid.uuid4().hex[:8]}", "--zenoh-port", str(zenoh), "--port-offset",
         str(offset), "--log-dir", str(tmp_path / "logs"), "--quiet", "--time-scale", "0.1",
         "--workers", "1"],
        env=dict(os.environ, AOI3D_TRAINER_RENDER_STEPS="30", AOI3D_SCHEDULER_POLICY="mat:70"),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    outside: list[str] = []
    try:
        for name in SERVICE_PORTS:
            wait_for(f"{name} /healthz",
                     lambda n=name: HTTP.get(url(n, "/healthz")).status_code == 200, 180)
        wait_for("a render", lambda: HTTP.get(url("trainer", "/render.png")).status_code == 200,
                 180)
        wait_for("a decision at the viewer",
                 lambda: HTTP.get(url("viewer", "/scene.json")).json()["decision"], 60)
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
                page.locator(".mantine-Notification-closeButton").first.click(timeout=5000)

            # the viewer asks the pool for its camera's view and shows it
            shown = wait_for("a free view shown", lambda: (
                d := HTTP.get(url("viewer", "/scene.json")).json())["views"]["shown"] >= 1
                and d, 90)
            page.wait_for_timeout(3000 * SCALE)  # the frustums' redraw, the image's decode
            before_c2w = HTTP.get(url("viewer", "/scene.json")).json()["views"]["last"]["c2w"]
            first = page.screenshot()

            # a frustum per camera, in the AoI colours of the decision in force
            doc = shown
            cameras = doc["cameras"]
            from aoi3d.scene import open_dataset

            ds = open_dataset(scene)
            assert [c["camera_id"] for c in cameras] == [
                i for i in range(1, min(18, len(ds.cameras) - 1) + 1) if i != ds.heldout_id]
            colours = {tuple(c["colour"]) for c in cameras if c["aoi_ms"] is not None}
            assert colours, doc
            for colour in colours:
                assert colour_pixels(first, list(colour)) >= 3, (colour, doc["cameras"])
            assert doc["decision"]["selected"] == sorted(
                c["camera_id"] for c in cameras if c["selected"])

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

            wait_for("a free view of the new pose", moved, 60)
            page.wait_for_timeout(3000 * SCALE)
            second = page.screenshot()
            from PIL import Image

            a = np.asarray(Image.open(io.BytesIO(first)).convert("RGB"), dtype=np.int16)
            b = np.asarray(Image.open(io.BytesIO(second)).convert("RGB"), dtype=np.int16)
            assert np.abs(a - b).mean() > 1.0
            (tmp_path / "viewer.png").write_bytes(second)
            target = os.environ.get("AOI3D_VIEWER_SCREENSHOT")
            if target:
                Path(target).write_bytes(second)
            browser.close()
        trainer_metrics = HTTP.get(url("trainer", "/metrics")).text
        assert 'aoi3d_trainer_views_total{kind="view",outcome="served"}' in trainer_metrics
        assert not outside, outside
    finally:
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGINT)
            try:
                up.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(up.pid, signal.SIGKILL)
                up.wait()
