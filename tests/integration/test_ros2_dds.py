"""A real ROS 2 robot on DDS (issue 43): an rclpy node from the ROS 2 wheels
(:mod:`tests.integration.ros2_dds_robot`) publishes the generated turbine — the truth camera and
four training cameras, raw (rgb8, bgr8) and compressed (jpeg, png) images, CameraInfo, and
PoseStamped and Odometry poses — on Fast DDS; ``aoi3d up --rig`` reads it with
``source.format: dds`` (no bridge, no Zenoh on the robot's side) and scores renders of it; a
real rclpy subscriber receives ``/aoi3d/render`` as an Image of the view's size.

The network rule: everything stays on 127.0.0.1 — Fast DDS's loopback profile (unicast
discovery through 127.0.0.1, no multicast) in a domain of the test's own; the test checks it
with ``ss -uanp`` while the robot and the ingest run: every UDP socket of theirs is bound to
127.0.0.1."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.support.metrics import samples
from tests.support.pipeline import HTTP, SCALE, assert_clean_exit, stop_pipeline, wait_for
from tests.support.rigpipe import PIPE, QualityTap, metric, up_rig, wait_healthy
from tests.support.ros2_dds import free_domain, loopback_env, need_rclpy

pytestmark = [pytest.mark.integration, pytest.mark.slow]

TIME_SCALE = 0.5
CAMERAS = 4
LINK_REFUSALS = {"no_pose", "no_intrinsics"}
"""The refusals a lossy DDS link causes (a pose or CameraInfo not received)."""


def descendants(pid: int) -> set[int]:
    """``pid`` and every process below it (from /proc)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            children.setdefault(ppid, []).append(int(entry))
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        out.add(p)
        todo += children.get(p, [])
    return out


def udp_sockets(pids: set[int]) -> list[tuple[str, int]]:
    """(local address, pid) of every UDP socket the processes hold (``ss -uanp``)."""
    text = subprocess.run(["ss", "-uanp"], capture_output=True, text=True, check=True).stdout
    out = []
    for line in text.splitlines()[1:]:
        for pid in map(int, re.findall(r"pid=(\d+)", line)):
            if pid in pids:
                out.append((line.split()[3], pid))
    return out


def test_a_real_rclpy_robot_on_dds_drives_the_pipeline_to_quality(
        small_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    need_rclpy()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image

    env: dict[str, str] = {}
    loopback_env(env)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    domain = free_domain()
    rig = tmp_path / "rig.yaml"
    robot_cmd = [sys.executable, "-m", "tests.integration.ros2_dds_robot", str(small_dataset),
                 "--domain", str(domain), "--cameras", str(CAMERAS), "--time-scale",
                 str(TIME_SCALE)]
    made = subprocess.run([*robot_cmd, "--write-rig", str(rig), "--rig-only"],
                          capture_output=True, text=True, timeout=120 * SCALE)
    assert made.returncode == 0, made.stderr
    up, run_id = up_rig(rig, tmp_path, "dds")
    robot = tap = None
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    viewer = rclpy.create_node("viewer", context=ctx)
    renders: list = []
    viewer.create_subscription(Image, "/aoi3d/render", renders.append, 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(viewer)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            try:
                ex.spin_once(timeout_sec=0.05)
            except Exception:
                return

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    try:
        wait_healthy()
        tap = QualityTap(run_id)
        robot = subprocess.Popen(robot_cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 text=True, start_new_session=True)
        wait_for("frames from the rclpy robot",
                 lambda: metric("ingest", "aoi3d_ingest_frames_total") >= 20, 90)
        # the network rule: the robot's and the pipeline's DDS sockets are on 127.0.0.1 only
        socks = udp_sockets(descendants(robot.pid) | descendants(up.pid))
        print("UDP sockets of the robot and the pipeline:", sorted(socks))
        assert socks, "no UDP socket of the robot or the ingest"
        assert all(addr.startswith("127.0.0.1:") for addr, _ in socks), socks
        status = HTTP.get(PIPE.url("ingest", "/status")).json()
        src = status["source"]
        assert src["format"] == "dds" and src["domain_id"] == domain
        # The ROS graph trails the data: the ingest polls DDS discovery every 0.5 s, and rclpy
        # names a discovered endpoint's node only once the robot's ros_discovery_info has come
        # (_NODE_NAME_UNKNOWN_ until then, ~0.1 s here). Frames can flow before /status shows
        # the robot (seen: publishers 0 on /cam00/image_raw with 20 frames in): wait for it.
        graph: dict = {}

        def robot_in_graph() -> bool:
            graph["topics"] = {t["topic"]: t for t in HTTP.get(PIPE.url(
                "ingest", "/status")).json()["source"]["graph"]["topics"]}
            return all(t["publishers"] == 1 and t["nodes"] == ["/dds_robot"]
                       for t in graph["topics"].values())

        waited = time.monotonic()
        try:
            wait_for("the robot's publishers in /status's ROS graph", robot_in_graph, 30)
        except AssertionError as err:
            raise AssertionError(f"{err}: {graph.get('topics')}") from None
        print(f"the robot complete in the graph after {time.monotonic() - waited:.2f} s more")
        kinds = {c["image_type"] for c in status["cameras"]}
        assert kinds == {"raw", "compressed"}, kinds
        wait_for("decisions", lambda: metric("scheduler", "aoi3d_decisions_total") > 3)
        wait_for("Quality of renders of the robot's frames", lambda: tap.quality, 150)
        with tap.lock:
            assert all(math.isfinite(q.psnr_db) for q in tap.quality)
            best = max(q.psnr_db for q in tap.quality)
        assert best > 10.0, best
        got = wait_for("/aoi3d/render at a real rclpy subscriber", lambda: renders, 60)[0]
        size = [c for c in status["cameras"] if c["role"] == "truth"]
        assert size and (got.width, got.height) == tuple(status["working_size"]), (
            got.width, got.height, status["working_size"])
        assert got.encoding == "rgb8" and len(got.data) == got.width * got.height * 3
        status = HTTP.get(PIPE.url("ingest", "/status")).json()
        print("refused:", {c["name"]: c["rejected"] for c in status["cameras"]},
              "published:", {c["name"]: c["published"] for c in status["cameras"]})
        for cam in status["cameras"]:
            assert cam["published"] > 0, cam
            # Refused: only what a lossy link causes. The robot's publishers match the
            # ingest's subscriptions one by one as DDS discovery goes, and a sensor-data
            # subscription is best effort, keep last 5: an image can come whose pose or
            # CameraInfo of its stamp was published before that topic matched, or dropped on
            # a busy machine. The ingest refuses that image (seen in 2 runs of 15: no_pose,
            # "the nearest pose on /cam04/odom is 0.060 s away", the next period's). Any
            # other reason, or more than one image in ten, is a fault of ours.
            assert set(cam["rejected"]) <= LINK_REFUSALS, cam
            assert sum(cam["rejected"].values()) <= max(2, cam["published"] // 10), cam
            assert cam["clock_offset_s"] is not None and abs(cam["clock_offset_s"]) < 1.0, cam
        text = HTTP.get(PIPE.url("ingest", "/metrics")).text
        reasons = {labels.get("reason") for name, labels, n in samples(text)
                   if name == "aoi3d_messages_rejected_total" and n > 0}
        assert reasons <= LINK_REFUSALS, reasons
    finally:
        stop.set()
        spinner.join(timeout=2)
        ex.shutdown(timeout_sec=1)
        viewer.destroy_node()
        ctx.shutdown()
        if robot is not None:
            robot.terminate()
            try:
                out, _ = robot.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                robot.kill()
        if tap is not None:
            tap.close()
        out = stop_pipeline(up)
    assert_clean_exit(up, out, run_id)
