"""The ingest service's FastAPI app: ``GET /status`` (the cameras, their counts, clock offsets
and the key format), plus the kit's ops routes."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI
from prometheus_client import CollectorRegistry

from aoi3d.rigfile import Rig, load_rig
from services import ros
from services.ingest.dds import DdsSource
from services.ingest.outputs import OutputTopics, RosOutputs, dds_sender, zenoh_sender
from services.ingest.runtime import IngestRuntime
from services.ingest.settings import Settings
from services.kit.app import get_worker, service_app
from services.kit.bus import Bus, ZenohBus
from services.kit.keys import Keys

DESCRIPTION = """
Real cameras in: subscribes to the rig file's ROS 2 topics on Zenoh (rmw_zenoh keys
`<domain>/<topic>/<type>/<hash>` or zenoh-bridge-ros2dds keys `[<namespace>/]<topic>`) or
straight on DDS (`source.format: dds`: a ROS 2 node of its own, rclpy on Fast DDS) and
publishes each image — resized to the working size, with the pose and intrinsics in force at
its stamp — as the pipeline's Frame where the camera emulator would: the truth camera on
`truth/frame`, the others on `edge/<n>/frame` delivered at their receipt (or `cam/<n>/frame`
when emulated delay is added on top). Generation time = `header.stamp` − the clock offset in
force. Bad samples are counted rejections with their reason. `GET /status` shows every
camera's counts, ages and measured clock offset. aoi3d's outputs go back into ROS on the
rig's source (on by default for DDS): the render and its CameraInfo, the decision with each
camera's AoI, and Quality (`AOI3D_INGEST_ROS_*`).
"""

WorkerDep = Annotated[IngestRuntime, Depends(get_worker)]

router = APIRouter(tags=["ingest"])


@router.get("/status", summary="The rig's cameras: counts, rejections by reason, losses, "
                               "frame ages and clock offsets; the key format and the link.")
def get_status(worker: WorkerDep) -> dict[str, Any]:
    return worker.status()


def robot_bus(connect: list[str]) -> ZenohBus:
    """A plain Zenoh client session to the robots' router (no credentials of the pipeline's
    own: the robots' router is theirs)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    return ZenohBus(conf)


def ros_outputs(settings: Settings, rig: Rig, bus: Bus, source: Any,
                keys: Keys) -> RosOutputs | None:
    """aoi3d's outputs in ROS on the rig's source (services.ingest.outputs), or None when off.
    ``source``: the ingest's DDS node (``format: dds``) or the bus the robots' topics are on."""
    dds = rig.source.format == "dds"
    if settings.ros_outputs == "off" or (settings.ros_outputs == "auto" and not dds):
        return None
    common = settings.common
    topics = OutputTopics(settings.ros_render_topic, settings.ros_camera_info_topic,
                          settings.ros_decision_topic, settings.ros_quality_topic)
    tokens: list[Any] = []
    if dds:
        sender = dds_sender(source)
    else:
        src = rig.source
        sender = zenoh_sender(source, ros.KeyFormat(src.format, src.domain_id, src.prefix),
                              tokens)

    def undeclare() -> None:
        for token in tokens:
            token.undeclare()

    return RosOutputs(bus=bus, keys=keys, rig=rig, epoch_s=common.epoch_s,
                      time_scale=common.time_scale, sender=sender, topics=topics,
                      on_stop=undeclare)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               rig: Rig | None = None, source: Bus | None = None,
               registry: CollectorRegistry | None = None) -> FastAPI:
    """The ingest service. ``rig`` defaults to ``load_rig(AOI3D_RIG)``; tests inject a
    ``MemoryBus`` (and a ``source`` bus standing for the robots' router)."""
    settings = settings or Settings()
    common = settings.common
    if rig is None:
        if common.rig is None:
            raise ValueError("the ingest service needs a rig file (AOI3D_RIG)")
        rig = load_rig(common.rig)

    def build_worker(the_bus: Bus, the_registry: CollectorRegistry) -> IngestRuntime:
        dds = rig.source.format == "dds"
        own = source is None and (bool(rig.source.connect) or dds)
        src: Any
        if own and dds:  # straight from DDS: the ingest's own ROS 2 node
            src = DdsSource(rig.source)
        else:
            src = robot_bus(rig.source.connect) if own else source
        keys = Keys(common.run_id, common.sites[0])
        return IngestRuntime(bus=the_bus, registry=the_registry, rig=rig,
                            keys=keys, epoch_s=common.epoch_s,
                            time_scale=common.time_scale, stall_s=common.stall_s,
                            through_network=settings.through_network,
                            wire_encoding=settings.wire_encoding,
                            inbox_size=settings.inbox_size, source=src, own_source=own,
                            outputs=ros_outputs(settings, rig, the_bus, src or the_bus, keys))

    app = service_app(title="aoi3d ingest", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus, registry=registry)
    app.include_router(router)
    return app
