"""Real ROS 2 (issue 43), in-process: rclpy nodes from the ROS 2 wheels on Fast DDS (127.0.0.1
only, a domain of the test's own) against the ingest's DDS source, aoi3d's outputs in ROS, and
the Zenoh path's CDR decoder.

- what rosidl serializes (rclpy's ``serialize_message``) and what a real publisher puts on the
  wire decode with :func:`services.ros.decode_cdr` to the same fields — the check the
  rmw_zenoh path never had;
- a rig with ``source.format: dds`` gets frames from a real publisher, its ``/status`` graph
  from DDS discovery and a ``/readyz`` that names the topic nobody publishes;
- ``/aoi3d/render`` (Image rgb8 + CameraInfo), the decision and Quality reach a real rclpy
  subscriber."""

from __future__ import annotations

import io
import threading
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image as PILImage

from aoi3d.rigfile import RigError, rig_from_dict
from services import ros
from services.ingest.app import create_app
from services.ingest.dds import DdsKeyFormat, parse_subscription
from services.ingest.fastdds import configure_fastdds, fastdds_profile, profile_folder
from services.ingest.settings import Settings
from services.kit.codec import decode_frame, encode_png
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from tests.support.ingest import C2W, INTR, OPTICAL, H, W, rig_doc
from tests.support.ros2_dds import free_domain, loopback_env, need_rclpy
from tests.support.waits import wait_for

RGB = np.random.default_rng(43).integers(0, 255, (H, W, 3), dtype=np.uint8)


def wait(check, what: str, timeout_s: float = 10.0):
    """Poll ``check`` every 50 ms (a publish per poll in most tests) until it holds, for
    ``timeout_s`` scaled by the one setting (tests/support/timeouts.py)."""
    return wait_for(check, timeout_s, what=what, every_s=0.05)


# ---------------------------------------------------------------- without ROS 2
def test_a_dds_source_in_the_rig() -> None:
    rig = rig_from_dict(rig_doc(source={"format": "dds", "domain_id": 42, "qos": "reliable",
                                        "depth": 2}))
    assert (rig.source.format, rig.source.domain_id, rig.source.interface) == ("dds", 42,
                                                                              "loopback")
    for bad in ({"format": "dds", "connect": ["tcp/127.0.0.1:7447"]},
                {"format": "dds", "namespace": "robot1"},
                {"format": "rmw_zenoh", "qos": "reliable"},
                {"format": "dds", "interface": "eth0"}):
        with pytest.raises(RigError):
            rig_from_dict(rig_doc(source=bad))
    fmt = DdsKeyFormat(domain_id=42)
    sub = fmt.subscription("cam0/image_raw", ros.IMAGE)
    assert parse_subscription(sub) == ("/cam0/image_raw", ros.IMAGE)
    assert not fmt.attached and fmt.check_key("anything", ros.IMAGE) is None


def test_the_loopback_profile_keeps_dds_on_127_0_0_1() -> None:
    root = ET.fromstring(fastdds_profile("loopback"))
    text = ET.tostring(root, encoding="unicode")
    addresses = {e.text for e in root.iter() if e.tag.endswith("address")}
    assert addresses == {"127.0.0.1"}, addresses
    assert "Multicast" not in text and "<ns0:useBuiltinTransports>false" in text
    assert fastdds_profile("all") is None
    assert "192.168.1.7" in fastdds_profile("192.168.1.7")


def test_configure_fastdds_sets_the_environment_once_per_profile(tmp_path) -> None:
    """The profile is a file of the user's (the same for every process: nothing left behind
    per start), named by its interface; ``all`` sets only the middleware."""
    env: dict[str, str] = {}
    out = configure_fastdds("loopback", environ=env)
    path = Path(out["FASTDDS_DEFAULT_PROFILES_FILE"])
    assert env == out and env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    assert path.parent == profile_folder() and path.read_text() == fastdds_profile("loopback")
    assert configure_fastdds("loopback", environ={}) == out  # the same file again
    lan = configure_fastdds("192.168.1.7", tmp_path, environ={})
    assert Path(lan["FASTDDS_DEFAULT_PROFILES_FILE"]).parent == tmp_path
    assert "192.168.1.7" in Path(lan["FASTDDS_DEFAULT_PROFILES_FILE"]).read_text()
    assert configure_fastdds("all", environ={}) == {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    assert not list(tmp_path.glob(".*.tmp"))


# ---------------------------------------------------------------- rclpy's messages
def rclpy_messages(stamp: float) -> dict:
    """One of each type the ingest reads, made with ROS 2's own message classes."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image

    sec, nsec = int(stamp), int((stamp - int(stamp)) * 1e9)

    def head(m, frame):
        m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id = sec, nsec, frame
        return m

    img = head(Image(), "cam1")
    img.height, img.width, img.encoding, img.step = H, W, "rgb8", W * 3
    img.data = RGB.tobytes()
    buf = io.BytesIO()
    PILImage.fromarray(RGB).save(buf, format="JPEG", quality=95)
    comp = head(CompressedImage(), "cam2")
    comp.format, comp.data = "jpeg", buf.getvalue()
    info = head(CameraInfo(), "cam1")
    info.height, info.width, info.distortion_model = H, W, "plumb_bob"
    info.d = [0.1, -0.2, 0.0, 0.0, 0.01]
    info.k = [20.0, 0.0, W / 2, 0.0, 21.0, H / 2, 0.0, 0.0, 1.0]
    info.p = [20.0, 0.0, W / 2, 0.0, 0.0, 21.0, H / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
    pose = head(PoseStamped(), "world")
    pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = 1.0, -2.0, 0.5
    q = (0.0, 0.0, np.sin(0.3), np.cos(0.3))
    (pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z,
     pose.pose.orientation.w) = q
    odom = head(Odometry(), "odom")
    odom.child_frame_id = "cam3"
    odom.pose.pose = pose.pose
    odom.pose.covariance = [float(i) for i in range(36)]
    odom.twist.twist.linear.x = 0.25
    return {ros.IMAGE: img, ros.COMPRESSED: comp, ros.CAMERA_INFO: info,
            ros.POSE_STAMPED: pose, ros.ODOMETRY: odom}


def assert_same(ros_type: str, sent, got) -> None:
    assert (got.header.stamp.sec, got.header.stamp.nanosec, got.header.frame_id) == (
        sent.header.stamp.sec, sent.header.stamp.nanosec, sent.header.frame_id)
    if ros_type == ros.IMAGE:
        assert (got.height, got.width, got.encoding, got.step) == (H, W, "rgb8", W * 3)
        assert np.array_equal(ros.image_rgb(got, ros_type, 10**7), RGB)
    elif ros_type == ros.COMPRESSED:
        assert got.format == "jpeg" and bytes(got.data) == bytes(sent.data)
        assert ros.image_rgb(got, ros_type, 10**7).shape == (H, W, 3)
    elif ros_type == ros.CAMERA_INFO:
        assert (got.height, got.width, got.distortion_model) == (H, W, "plumb_bob")
        assert list(got.k) == list(sent.k) and list(got.d) == list(sent.d)
        assert list(got.p) == list(sent.p)
        assert ros.camera_info(got) == ros.Intrinsics(20.0, 21.0, W / 2, H / 2, W, H)
    else:
        m = ros.pose_matrix(got, ros_type)
        assert np.allclose(m[:3, 3], [1.0, -2.0, 0.5])
        assert np.isclose(np.arctan2(m[1, 0], m[0, 0]), 0.6)
        if ros_type == ros.ODOMETRY:
            assert got.child_frame_id == "cam3" and list(got.pose.covariance) == list(range(36))
            assert got.twist.twist.linear.x == 0.25


def test_the_zenoh_path_decodes_what_rosidl_serializes() -> None:
    need_rclpy()
    from rclpy.serialization import serialize_message

    stamp = time.time()
    for ros_type, msg in rclpy_messages(stamp).items():
        cdr = serialize_message(msg)
        assert_same(ros_type, msg, ros.decode_cdr(cdr, ros_type, 10**7))
        # rosbags' encoding of what it decoded is rosidl's layout: the same length and the
        # same bytes but the alignment padding (Fast CDR leaves whatever was in its buffer
        # there: seen here, 'U' after a frame_id), which decoders must ignore
        again = ros.encode_cdr(ros.decode_cdr(cdr, ros_type, 10**7), ros_type)
        assert len(again) == len(cdr), ros_type
        assert ros.decode_cdr(again, ros_type, 10**7) is not None


@pytest.fixture
def dds(monkeypatch):
    """Fast DDS on 127.0.0.1 in a domain of this test's own; yields (domain, rclpy context),
    the context a test's own nodes live in."""
    need_rclpy()
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    env: dict[str, str] = {}
    loopback_env(env)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    domain = free_domain()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    yield domain, ctx
    ctx.shutdown()


class Spinner:
    """An executor thread over a test's nodes."""

    def __init__(self, ctx, *nodes) -> None:
        from rclpy.executors import SingleThreadedExecutor

        self.ex = SingleThreadedExecutor(context=ctx)
        for n in nodes:
            self.ex.add_node(n)
        self.stop = threading.Event()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            try:
                self.ex.spin_once(timeout_sec=0.05)
            except Exception:
                return

    def close(self) -> None:
        self.stop.set()
        self.t.join(timeout=2)
        self.ex.shutdown(timeout_sec=1)


def test_messages_captured_on_the_dds_wire_decode_the_same(dds) -> None:
    """A real publisher (sensor-data QoS) and a raw subscriber: the bytes Fast DDS carried,
    decoded by the Zenoh path's decoder."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data

    from services.ingest.dds import message_class

    _domain, ctx = dds
    node = rclpy.create_node("wire_probe", context=ctx)
    got: dict[str, list[bytes]] = {t: [] for t in ros.TYPES}
    pubs = {}
    for i, t in enumerate(ros.TYPES):
        topic = f"/probe/t{i}"
        pubs[t] = node.create_publisher(message_class(t), topic, qos_profile_sensor_data)
        node.create_subscription(message_class(t), topic, got[t].append,
                                 qos_profile_sensor_data, raw=True)
    spin = Spinner(ctx, node)
    try:
        msgs = rclpy_messages(time.time())

        def all_came() -> bool:
            for t, m in msgs.items():
                if not got[t]:
                    pubs[t].publish(m)
            return all(got.values())

        wait(all_came, "each type back off the wire", 20)
        for t, m in msgs.items():
            assert_same(t, m, ros.decode_cdr(got[t][0], t, 10**7))
    finally:
        spin.close()
        node.destroy_node()


def dds_rig(domain: int):
    return rig_from_dict(rig_doc(source={"format": "dds", "domain_id": domain}))


def test_a_dds_robot_feeds_the_ingest(dds) -> None:
    """A real rclpy robot (Image, CameraInfo, PoseStamped on cam1; nobody on cam2): the
    ingest's readiness names cam2's topic from DDS discovery, then frames come, /status shows
    the graph, and the render goes back out as /aoi3d/render to a real subscriber."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import qos_profile_sensor_data
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import CameraInfo, Image

    domain, ctx = dds
    bus, keys = MemoryBus(), Keys("t")
    settings = Settings(common=CommonSettings(run_id="t", cameras=3, epoch_s=time.time() - 60))
    robot = rclpy.create_node("dds_robot", namespace="/rig", context=ctx)
    pub_img = robot.create_publisher(Image, "/cam1/image_raw", qos_profile_sensor_data)
    pub_info = robot.create_publisher(CameraInfo, "/cam1/camera_info", qos_profile_sensor_data)
    pub_pose = robot.create_publisher(PoseStamped, "/cam1/pose", qos_profile_sensor_data)
    renders: list = []
    viewer = rclpy.create_node("viewer", context=ctx)
    viewer.create_subscription(Image, "/aoi3d/render", renders.append, 10)
    spin = Spinner(ctx, robot, viewer)
    try:
        with TestClient(create_app(settings, bus=bus, rig=dds_rig(domain))) as client:
            # DDS discovery fills the graph endpoint by endpoint (polled every 0.5 s): the
            # readiness may name cam1's topic too until its publisher is discovered
            last: dict[str, str] = {}

            def hint() -> bool:
                r = client.get("/readyz")
                last["readyz"] = r.text
                return (r.status_code == 503 and "/cam2/image_raw/compressed" in r.text
                        and "/cam1/image_raw" not in r.text)

            try:
                wait(hint, "readiness naming only the unpublished topic", 20)
            except AssertionError as err:
                raise AssertionError(f"{err}: {last}") from None
            # the robot publishes once its publishers have matched the ingest's subscriptions
            # (DDS matches each on its own; what a publisher sends before is dropped, and an
            # image whose pose was would be refused: tests/integration/test_ros2_dds.py)
            wait(lambda: all(p.get_subscription_count() >= 1
                             for p in (pub_img, pub_info, pub_pose)),
                 "the robot's publishers matched", 20)
            m = C2W @ OPTICAL
            x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()

            def publish() -> int:
                msgs = rclpy_messages(time.time())
                img, info = msgs[ros.IMAGE], msgs[ros.CAMERA_INFO]
                info.k = [INTR["fx"], 0.0, INTR["cx"], 0.0, INTR["fy"], INTR["cy"], 0, 0, 1.0]
                pose = PoseStamped()
                pose.header = img.header
                pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = m[:3, 3]
                (pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z,
                 pose.pose.orientation.w) = x, y, z, w
                pub_info.publish(info)
                pub_pose.publish(pose)
                pub_img.publish(img)
                return len([k for k, _ in bus.published if k == keys.edge_frame(1)])

            wait(lambda: publish() >= 3, "frames from the DDS robot", 30)
            frame = decode_frame(next(p for k, p in bus.published if k == keys.edge_frame(1)))
            assert frame.camera_id == 1
            assert np.allclose(np.asarray(frame.camera.c2w), C2W, atol=1e-5)
            # rclpy names a discovered publisher's node once ros_discovery_info has come
            # (_NODE_NAME_UNKNOWN_ until then), and the graph is polled: wait for the name
            def named() -> dict:
                status = client.get("/status").json()
                topics = {t["topic"]: t for t in status["source"]["graph"]["topics"]}
                last["topics"] = repr(topics)
                cam1 = topics["/cam1/image_raw"]
                return status if cam1["nodes"] == ["/rig/dds_robot"] else {}

            try:
                status = wait(named, "the robot's node in /status's graph", 20)
            except AssertionError as err:
                raise AssertionError(f"{err}: {last}") from None
            src = status["source"]
            assert src["format"] == "dds" and src["domain_id"] == domain
            assert src["qos"]["reliability"] == "best_effort"
            topics = {t["topic"]: t for t in src["graph"]["topics"]}
            assert topics["/cam1/image_raw"]["publishers"] == 1
            assert topics["/cam2/image_raw/compressed"]["publishers"] == 0
            cam1 = next(c for c in status["cameras"] if c["name"] == "cam1")
            assert cam1["published"] >= 3 and cam1["rejected"] == {}, cam1
            assert client.get("/readyz").status_code == 200
            metrics = client.get("/metrics").text
            assert 'aoi3d_ingest_ros_publishers{topic="/cam1/image_raw"} 1.0' in metrics

            # aoi3d's outputs: a render of the view goes out as /aoi3d/render
            view = np.random.default_rng(1).integers(0, 255, (H, W, 3), dtype=np.uint8)
            render = pb.Render(decision_id=7, time_ms=60_000.0, image=encode_png(view),
                               intrinsics=pb.Intrinsics(fx=20, fy=20, cx=W / 2, cy=H / 2,
                                                        width=W, height=H))

            def rendered():
                bus.publish(keys.render, render.SerializeToString())
                return renders

            got = wait(rendered, "the render on /aoi3d/render", 20)[0]
            assert (got.width, got.height, got.encoding) == (W, H, "rgb8")
            assert np.array_equal(np.frombuffer(bytes(got.data), np.uint8).reshape(H, W, 3),
                                  view)
            stamp = got.header.stamp.sec + got.header.stamp.nanosec * 1e-9
            common = settings.common  # the decision time, on the pipeline's clock
            assert abs(stamp - (common.epoch_s + 60.0 / common.time_scale)) < 1e-3
    finally:
        spin.close()
        robot.destroy_node()
        viewer.destroy_node()


def test_the_outputs_reach_rclpy_subscribers(dds) -> None:
    """Render (Image rgb8 + CameraInfo), decision (AoI per camera) and Quality, on a DDS
    source, received by a real rclpy node as ROS 2's own message classes."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import CameraInfo, Image

    from services.ingest.dds import DdsSource
    from services.ingest.outputs import OutputTopics, RosOutputs, dds_sender

    domain, ctx = dds
    rig = dds_rig(domain)
    source = DdsSource(rig.source)
    bus, keys = MemoryBus(), Keys("t")
    topics = OutputTopics(render="/view/image", camera_info="/view/camera_info",
                          decision="/view/aoi", quality="/view/quality")
    out = RosOutputs(bus=bus, keys=keys, rig=rig, epoch_s=1000.0, time_scale=0.5,
                     sender=dds_sender(source), topics=topics)
    out.start()
    got: dict[str, list] = {"image": [], "info": [], "aoi": [], "quality": []}
    sub = rclpy.create_node("sub", context=ctx)
    sub.create_subscription(Image, "/view/image", got["image"].append, 10)
    sub.create_subscription(CameraInfo, "/view/camera_info", got["info"].append, 10)
    sub.create_subscription(DiagnosticArray, "/view/aoi", got["aoi"].append, 10)
    sub.create_subscription(DiagnosticArray, "/view/quality", got["quality"].append, 10)
    spin = Spinner(ctx, sub)
    ids = rig.ids()
    try:
        view = np.random.default_rng(2).integers(0, 255, (H, W, 3), dtype=np.uint8)
        msgs = [
            (keys.render, pb.Render(decision_id=3, time_ms=500.0, image=encode_png(view),
                                    intrinsics=pb.Intrinsics(fx=20, fy=21, cx=W / 2, cy=H / 2,
                                                             width=W, height=H))),
            (keys.decision, pb.Decision(decision_id=3, time_ms=500.0, policy="mat:70",
                                        camera_ids=[ids["cam1"], ids["cam2"]],
                                        aoi_ms=[40.0, float("nan")],
                                        selected=[pb.FrameRef(camera_id=ids["cam1"])])),
            (keys.quality, pb.Quality(decision_id=3, time_ms=500.0, psnr_db=23.5, ssim=0.8,
                                      display_time_ms=560.0, psnr_display_db=21.25)),
        ]

        def all_came() -> bool:
            for key, m in msgs:
                bus.publish(key, m.SerializeToString())
            return all(got.values())

        wait(all_came, "every output at the subscriber", 20)
        img, info = got["image"][0], got["info"][0]
        assert (img.width, img.height, img.encoding, img.header.frame_id) == (W, H, "rgb8",
                                                                             "aoi3d_view")
        assert (img.header.stamp.sec, img.header.stamp.nanosec) == (1001, 0)  # 1000 + 0.5/0.5
        assert list(info.k) == [20.0, 0.0, W / 2, 0.0, 21.0, H / 2, 0.0, 0.0, 1.0]
        assert info.header.stamp == img.header.stamp
        status = {s.name: {kv.key: kv.value for kv in s.values} for s in got["aoi"][0].status}
        assert status["decision"]["decision_id"] == "3" and status["decision"]["selected"] == \
            "cam1"
        assert status["cam1"] == {"aoi_ms": "40", "selected": "true"}
        assert status["cam2"] == {"aoi_ms": "nan", "selected": "false"}
        q = {kv.key: kv.value for kv in got["quality"][0].status[0].values}
        assert (q["psnr_db"], q["psnr_display_db"], q["display_time_ms"]) == ("23.5", "21.25",
                                                                             "560")
    finally:
        spin.close()
        sub.destroy_node()
        out.stop()
        source.close()


def test_the_outputs_on_rmw_zenoh_keys() -> None:
    """Without DDS: with ``AOI3D_INGEST_ROS_OUTPUTS=on`` on an rmw_zenoh rig, the render goes
    out on rmw_zenoh's key with its attachment, and node ``/aoi3d`` announces its publishers
    in the ROS graph's tokens (off by default on Zenoh keys: nothing goes out)."""
    from services.ingest.outputs import NODE

    rig = rig_from_dict(rig_doc(source={"format": "rmw_zenoh", "domain_id": 3}))
    keys = Keys("t")
    view = np.random.default_rng(5).integers(0, 255, (H, W, 3), dtype=np.uint8)
    render = pb.Render(decision_id=1, time_ms=0.0, image=encode_png(view),
                       intrinsics=pb.Intrinsics(fx=20, fy=20, cx=W / 2, cy=H / 2, width=W,
                                                height=H)).SerializeToString()
    for outputs, expect in (("auto", 0), ("on", 1)):
        bus, seen = MemoryBus(), []
        bus.subscribe_attached("3/aoi3d/render/**",
                               lambda k, p, a, seen=seen: seen.append((k, p, a)))
        settings = Settings(ros_outputs=outputs,
                            common=CommonSettings(run_id="t", cameras=3, epoch_s=time.time()))
        with TestClient(create_app(settings, bus=bus, rig=rig)):
            tokens = [k for k in bus._tokens if k.split("/")[8] == NODE]
            bus.publish(keys.render, render)
        assert len(seen) == expect, seen
        if expect:
            key, payload, att = seen[0]
            assert key == ros.KeyFormat("rmw_zenoh", 3).key("/aoi3d/render", ros.IMAGE)
            assert ros.parse_attachment(att).sequence == 1
            img = ros.decode_cdr(payload, ros.IMAGE, 10**7)
            assert np.array_equal(ros.image_rgb(img, ros.IMAGE, 10**7), view)
            graph = [ros.parse_liveliness(t) for t in tokens]
            assert {(e.kind, e.topic) for e in graph} >= {("node", None),
                                                          ("publisher", "/aoi3d/render")}
