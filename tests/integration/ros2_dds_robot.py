"""A real ROS 2 robot for the tests (issue 43): an rclpy node from the ROS 2 wheels on Fast DDS
(127.0.0.1 only) playing the generated turbine with ROS 2's own message classes and
serialization — the truth camera and N training cameras, raw (``rgb8``/``bgr8`` Image) and
compressed (jpeg/png CompressedImage) in turn, each with its CameraInfo and a pose topic,
PoseStamped and Odometry in turn. Images go with the sensor-data QoS camera drivers use (best
effort, keep last 5), CameraInfo and poses with ROS 2's default (reliable, keep last 10).

``python -m tests.integration.ros2_dds_robot DATASET --domain D --cameras N --time-scale S
[--write-rig RIG [--rig-only]]``: ``--write-rig`` writes the rig file (``source.format: dds``)
that reads exactly what it publishes."""

from __future__ import annotations

import argparse
import io
import math
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from services.ingest.fastdds import configure_fastdds

OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])
IMAGES = ("rgb8", "jpeg", "bgr8", "png")
NODE = "dds_robot"


def plan(ds, cameras: int) -> list[dict]:
    """Per camera: id, name, image kind, pose type, topics."""
    train = sorted(int(i) for i in ds.train_ids)[:cameras]
    out = [{"id": int(ds.heldout_id), "name": f"cam{int(ds.heldout_id):02d}", "image": "rgb8",
            "pose": None}]
    for i, n in enumerate(train):
        out.append({"id": n, "name": f"cam{n:02d}", "image": IMAGES[i % len(IMAGES)],
                    "pose": "PoseStamped" if i % 2 == 0 else "Odometry"})
    for c in out:
        base = f"/{c['name']}"
        c["image_topic"] = base + "/image_raw" + (
            "/compressed" if c["image"] in ("jpeg", "png") else "")
        c["info_topic"] = base + "/camera_info"
        c["pose_topic"] = base + ("/odom" if c["pose"] == "Odometry" else "/pose")
    return out


def rig_document(ds, cameras: int, domain: int, time_scale: float, period_ms: float) -> dict:
    cams = []
    for c in plan(ds, cameras):
        cam = ds.cameras[c["id"]]
        static = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
                  "height": cam.height}
        if c["pose"] is None:  # the truth camera: the rendered view, static in the file
            entry = {"intrinsics": static, "pose": {
                "c2w": [float(x) for x in np.asarray(cam.c2w).ravel()], "convention": "opengl"}}
        else:
            entry = {"intrinsics": {"camera_info": c["info_topic"]},
                     "pose": {"topic": c["pose_topic"], "type": c["pose"],
                              "convention": "optical"}}
        cams.append({"name": c["name"], "image": c["image_topic"], **entry})
    return {"source": {"format": "dds", "domain_id": domain, "qos": "sensor_data"},
            "cameras": cams, "truth": cams[0]["name"],
            "aabb": [float(x) for x in np.asarray(ds.aabb).ravel()],
            "size": [int(ds.cameras[0].width), int(ds.cameras[0].height)],
            "time_scale": time_scale, "truth_period_ms": period_ms}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--domain", type=int, required=True)
    ap.add_argument("--cameras", type=int, default=3)
    ap.add_argument("--time-scale", type=float, default=0.5)
    ap.add_argument("--period-ms", type=float, default=30.0)
    ap.add_argument("--duration-s", type=float, default=600.0)
    ap.add_argument("--write-rig", type=Path)
    ap.add_argument("--rig-only", action="store_true")
    a = ap.parse_args(argv)
    from aoi3d.scene import open_dataset

    ds = open_dataset(a.dataset)
    if a.write_rig:
        a.write_rig.write_text(yaml.safe_dump(rig_document(ds, a.cameras, a.domain,
                                                           a.time_scale, a.period_ms)))
        if a.rig_only:
            return 0
    configure_fastdds("loopback")
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from PIL import Image as PILImage
    from rclpy.qos import qos_profile_sensor_data
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image

    rclpy.init(domain_id=a.domain)
    node = rclpy.create_node(NODE)
    cams = plan(ds, a.cameras)
    pubs = {}
    for c in cams:
        compressed = c["image"] in ("jpeg", "png")
        pubs[c["name"]] = {
            "image": node.create_publisher(CompressedImage if compressed else Image,
                                           c["image_topic"], qos_profile_sensor_data),
            "info": node.create_publisher(CameraInfo, c["info_topic"], 10),
            "pose": (node.create_publisher(Odometry if c["pose"] == "Odometry" else PoseStamped,
                                           c["pose_topic"], 10) if c["pose"] else None)}
    stop = threading.Event()
    spin = threading.Thread(target=lambda: rclpy.spin(node), daemon=True)
    spin.start()

    def header(m, stamp: float, frame: str):
        sec = math.floor(stamp)
        m.header.stamp.sec, m.header.stamp.nanosec = sec, min(int((stamp - sec) * 1e9),
                                                              999_999_999)
        m.header.frame_id = frame
        return m

    period_wall = a.period_ms / 1000.0 / a.time_scale
    start, k, sent = time.time(), 0, 0
    try:
        while rclpy.ok() and not stop.is_set() and k * period_wall < a.duration_s:
            due = start + k * period_wall
            late = math.floor((time.time() - start) / period_wall)
            if late > k:
                k = late
                continue
            time.sleep(max(0.0, due - time.time()))
            index = ds.frame_index(k * a.period_ms)
            for c in cams:
                cam, p = ds.cameras[c["id"]], pubs[c["name"]]
                if c["pose"]:
                    m = np.asarray(cam.c2w) @ OPTICAL
                    x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
                    msg = header(Odometry() if c["pose"] == "Odometry" else PoseStamped(), due,
                                 "world")
                    pose = msg.pose.pose if c["pose"] == "Odometry" else msg.pose
                    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in
                                                                         m[:3, 3])
                    (pose.orientation.x, pose.orientation.y, pose.orientation.z,
                     pose.orientation.w) = (float(x), float(y), float(z), float(w))
                    if c["pose"] == "Odometry":
                        msg.child_frame_id = c["name"]
                    p["pose"].publish(msg)
                info = header(CameraInfo(), due, c["name"])
                info.width, info.height, info.distortion_model = cam.width, cam.height, \
                    "plumb_bob"
                info.d = [0.0] * 5
                info.k = [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0]
                info.r = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
                info.p = [cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
                p["info"].publish(info)
                rgb = np.ascontiguousarray(ds.frame(c["id"], index), dtype=np.uint8)
                if c["image"] in ("jpeg", "png"):
                    buf = io.BytesIO()
                    PILImage.fromarray(rgb).save(buf, format="JPEG" if c["image"] == "jpeg"
                                                 else "PNG")
                    img = header(CompressedImage(), due, c["name"])
                    img.format, img.data = c["image"], buf.getvalue()
                else:
                    img = header(Image(), due, c["name"])
                    h, w = rgb.shape[:2]
                    img.height, img.width, img.encoding, img.step = h, w, c["image"], w * 3
                    img.data = (rgb[:, :, ::-1] if c["image"] == "bgr8" else rgb).tobytes()
                p["image"].publish(img)
                sent += 1
            k += 1
    except Exception as err:  # SIGTERM/SIGINT: rclpy shut its context down under the loop
        if rclpy.ok():
            raise
        print(f"stopped: {err!r}", flush=True)
    finally:
        print(f"published {sent} images", flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
