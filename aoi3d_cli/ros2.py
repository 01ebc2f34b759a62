"""``aoi3d ros2 …``: real cameras over ROS 2 and Zenoh.

``aoi3d ros2 publish DATASET`` is a pure-Python robot (:mod:`services.ros.robot`): it
plays any dataset aoi3d reads as ROS 2 cameras — images, camera info and poses — on rmw_zenoh
keys (Jazzy's type hash or Humble's placeholder) or zenoh-bridge-ros2dds keys, at any rate and
time scale, and writes the rig file that reads them (``--write-rig``), for ``aoi3d up --rig``.
``aoi3d ros2 check RIG`` validates a rig file (any source: rmw_zenoh, bridge or dds).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from aoi3d_cli.common import fail, fail_lines, stop_on_signal

if TYPE_CHECKING:
    from aoi3d.scene import SceneDataset
    from services.ros.robot import PublishConfig

app = typer.Typer(no_args_is_help=True, add_completion=False)


@app.callback()
def ros2() -> None:
    """Real cameras: ROS 2 over Zenoh (rmw_zenoh or zenoh-bridge-ros2dds)."""


@app.command()
def publish(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder aoi3d reads (the turbine, "
                                                 "D-NeRF, DyNeRF…).")],
    key_format: Annotated[str, typer.Option(
        "--format", help="rmw_zenoh (<domain>/<topic>/<type>/<hash>, with the attachment) or "
                         "bridge (zenoh-bridge-ros2dds: [<namespace>/]<topic>).")] = "rmw_zenoh",
    distro: Annotated[str, typer.Option(
        help="rmw_zenoh's type hash in the keys: jazzy (RIHS01_<hex>) or humble "
             "(TypeHashNotSupported).")] = "jazzy",
    domain_id: Annotated[int, typer.Option(min=0, max=232, help="ROS_DOMAIN_ID "
                                                                 "(rmw_zenoh).")] = 0,
    namespace: Annotated[str, typer.Option(help="The bridge's namespace (a key prefix).")] = "",
    connect: Annotated[str, typer.Option(
        help="Zenoh endpoint(s) to connect to, comma-separated.")] = "tcp/127.0.0.1:7447",
    period_ms: Annotated[float | None, typer.Option(
        help="Scene ms between two frames of a camera (default 30, the emulator's "
             "period).")] = None,
    rate: Annotated[float | None, typer.Option(
        help="Frames per scene second of each camera (instead of --period-ms).")] = None,
    time_scale: Annotated[float, typer.Option(
        help="Scene seconds per wall second (0.1: ten times slower; give `aoi3d up --rig` the "
             "same, the rig file written says it).")] = 1.0,
    cameras: Annotated[int | None, typer.Option(
        help="Training cameras 1..N of the dataset (default all).")] = None,
    image: Annotated[str, typer.Option(
        help="rgb8 or bgr8 (sensor_msgs/Image), jpeg or png (CompressedImage).")] = "rgb8",
    intrinsics: Annotated[str, typer.Option(
        help="topic (CameraInfo on /camNN/camera_info) or file (values in the rig "
             "file).")] = "topic",
    pose: Annotated[str, typer.Option(
        help="topic (PoseStamped on /camNN/pose), odometry (Odometry on /camNN/odom) or file "
             "(static in the rig file).")] = "topic",
    truth: Annotated[bool, typer.Option(
        help="Publish the dataset's held-out view as cam00, the rig's truth camera.")] = True,
    clock_offset_s: Annotated[float, typer.Option(
        help="The robot's clock minus the true time, in seconds (a robot whose clock is "
             "off).")] = 0.0,
    duration_s: Annotated[float | None, typer.Option(
        help="Stop after this many wall seconds (default: until Ctrl-C).")] = None,
    epoch_s: Annotated[float | None, typer.Option(
        help="Phase-lock to a pipeline's clock (its epoch, Unix s: the ingest's GET /status "
             "shows time.epoch_s): frame k at epoch + k·period / time scale, showing scene "
             "time k·period, exactly as the camera emulator's. Default: the robot's own "
             "start (any phase).")] = None,
    write_rig: Annotated[Path | None, typer.Option(
        help="Write the rig file that reads what is published (YAML, or JSON for .json), "
             "for `aoi3d up --rig`.")] = None,
    rig_only: Annotated[bool, typer.Option(
        help="Write the rig file (--write-rig) and exit without publishing.")] = False,
) -> None:
    """Play DATASET as ROS 2 cameras on Zenoh: each camera's image, camera info and pose,
    stamped with the robot's clock, every period."""
    from services.ros.robot import PublishConfig

    period_ms = _period_ms(period_ms, rate)
    try:
        cfg = PublishConfig(dataset=dataset, format=key_format, distro=distro,
                            domain_id=domain_id, namespace=namespace,
                            connect=[c.strip() for c in connect.split(",") if c.strip()],
                            period_ms=30.0 if period_ms is None else period_ms,
                            time_scale=time_scale, cameras=cameras, image=image,
                            intrinsics=intrinsics, pose=pose, truth=truth,
                            clock_offset_s=clock_offset_s, duration_s=duration_s,
                            epoch_s=epoch_s)
    except ValueError as err:
        fail(str(err))
    ds, doc = _dataset_and_rig(cfg)
    if write_rig is not None:
        write_rig_file(write_rig, doc)
        typer.echo(f"rig file: {write_rig} (aoi3d up --rig {write_rig})")
    if rig_only:
        if write_rig is None:
            raise typer.BadParameter("needs --write-rig", param_hint="'--rig-only'")
        return
    _play(cfg, ds)


def _period_ms(period_ms: float | None, rate: float | None) -> float | None:
    """--period-ms, or the period --rate stands for (not both)."""
    if period_ms is not None and rate is not None:
        raise typer.BadParameter("give --period-ms or --rate, not both", param_hint="'--rate'")
    if rate is not None:
        if not rate > 0:
            raise typer.BadParameter("must be > 0", param_hint="'--rate'")
        period_ms = 1000.0 / rate
    return period_ms


def _dataset_and_rig(cfg: PublishConfig) -> tuple[SceneDataset, dict[str, Any]]:
    """The dataset played and the rig file that reads what is published."""
    from aoi3d.scene import open_dataset
    from services.ros.robot import rig_document

    ds = open_dataset(cfg.dataset)
    try:
        doc = rig_document(cfg, ds)
    except ValueError as err:
        fail(str(err))
    return ds, doc


def _play(cfg: PublishConfig, ds: SceneDataset) -> None:
    """Publish as the robot until Ctrl-C (or cfg.duration_s), a line before and after."""
    from services.ros.publishing import zenoh_publishing
    from services.ros.robot import Robot

    # the robot knows its keys; the session waits until they are subscribed (zenoh_publishing)
    robot = Robot(cfg, lambda *sample: put(*sample), dataset=ds)
    where = (f"rmw_zenoh keys (domain {cfg.domain_id}, {cfg.distro})"
             if cfg.format == "rmw_zenoh" else f"bridge keys (namespace '{cfg.namespace}')")
    typer.echo(f"publishing {len(robot.ids)} cameras of {cfg.dataset} on {where} via "
               f"{', '.join(cfg.connect)}: one frame each every {cfg.period_ms:g} scene ms at "
               f"time scale {cfg.time_scale:g}; e.g. {robot.keys()[0]}")
    t0 = time.monotonic()
    with zenoh_publishing(cfg.connect, robot.keys(), tokens=robot.tokens) as put, \
            stop_on_signal() as stop:
        robot.run(stop)
    typer.echo(f"published {robot.frames_sent} images in {robot.periods} periods over "
               f"{time.monotonic() - t0:.1f} s ({robot.skipped} periods skipped: behind)")


@app.command()
def rtsp(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder aoi3d reads.")],
    url: Annotated[str, typer.Option(help="Where to push: an ingest listening there (a rig "
                                          "camera with url: this, listen: true).")],
    camera: Annotated[int, typer.Option(help="The dataset's camera to stream.")] = 1,
    period_ms: Annotated[float, typer.Option(help="Scene ms between two frames.")] = 30.0,
    time_scale: Annotated[float, typer.Option(help="Scene seconds per wall second.")] = 1.0,
    duration_s: Annotated[float | None, typer.Option(
        help="Stop after this many wall seconds (default: until Ctrl-C).")] = None,
) -> None:
    """An IP camera: stream one of DATASET's cameras as H.264 over RTSP (pushed: RECORD)."""
    from aoi3d.scene import open_dataset
    from services.ros.rtsp import push_rtsp

    ds = open_dataset(dataset)
    if not 0 <= camera < len(ds.cameras):
        raise typer.BadParameter(f"0..{len(ds.cameras) - 1}", param_hint="'--camera'")
    typer.echo(f"pushing camera {camera} of {dataset} as H.264 to {url}")
    with stop_on_signal() as stop:
        try:
            sent = push_rtsp(ds, camera, url, period_ms=period_ms, time_scale=time_scale,
                             stop=stop, duration_s=duration_s)
        except Exception as err:  # av's connection errors: one line
            fail(f"{url}: {err}")
    typer.echo(f"sent {sent} frames")


@app.command()
def check(rig: Annotated[Path, typer.Argument(help="A rig file (YAML or JSON).")]) -> None:
    """Validate a rig file: one line per bad field, naming it (and each video file that is not
    there); else a summary."""
    from aoi3d.rigfile import RigError, load_rig

    try:
        r = load_rig(rig, videos=True)
    except RigError as err:
        fail_lines(err)
    ids = r.ids()
    src = r.source
    source = (f"DDS straight (domain {src.domain_id}, {src.interface})" if src.format == "dds"
              else f"{src.format} keys")
    typer.echo(f"{rig}: {len(r.train)} training cameras, truth "
               f"{r.truth or '(none: renders cannot be scored)'}, {source}, "
               f"working size {r.working_size[0]}x{r.working_size[1]}, time scale "
               f"{r.time_scale:g}")
    for c in r.cameras:
        typer.echo(f"  {ids[c.name]:3d} {c.name}: {c.image or c.url} ({c.kind}), intrinsics "
                   f"{'static' if c.intrinsics.static else c.intrinsics.camera_info}, pose "
                   f"{'static' if c.pose.static else c.pose.topic}")


def write_rig_file(path: Path, doc: dict) -> None:
    import json

    from aoi3d.atomic import write_atomic

    if path.suffix.lower() == ".json":
        text = json.dumps(doc, indent=2) + "\n"
    else:
        import yaml

        text = ("# aoi3d rig file (docs/real-cameras.md), written by `aoi3d ros2 publish` or "
                "`aoi3d replay --live`\n"
                + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, text)
