"""Settings of the ingest service (environment prefix ``AOI3D_INGEST_``); the rig file itself
is the run's (``AOI3D_RIG``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.kit.settings import ServiceSettings


class Settings(ServiceSettings):
    """Real cameras in: ROS 2 images (rmw_zenoh or zenoh-bridge-ros2dds keys, or straight from
    DDS) with their poses and intrinsics, as the pipeline's frames; and aoi3d's outputs back in
    ROS (services.ingest.outputs)."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_INGEST_", extra="ignore")

    port: int = Field(8101, ge=0, le=65535, description="REST API port (the camera "
                                                        "emulator's: ingest takes its place).")
    through_network: bool = Field(
        False, description="Publish the training cameras' frames on cam/<n>/frame, for the "
                           "network service to add its emulated delay on top of the real link "
                           "(from each frame's receipt); else on edge/<n>/frame, delivered at "
                           "receipt (the network emulator steps aside). `aoi3d up --rig "
                           "--delay SPEC` sets it.")
    wire_encoding: Literal["png", "raw"] = Field(
        "png", description="Images on the pipeline's wire: png (small, ~1 ms per 96x72 "
                           "frame to encode) or raw RGB (no encoding; large frames).")
    inbox_size: int = Field(512, ge=1, le=65536,
                            description="Samples buffered between Zenoh and the decoding "
                                        "thread (the oldest dropped, counted).")
    ros_outputs: Literal["auto", "on", "off"] = Field(
        "auto", description="Publish the render, its camera info, the decision (AoI per camera) "
                            "and Quality as ROS 2 topics on the rig's source "
                            "(services.ingest.outputs): on, off, or auto (on for a dds source, "
                            "off on Zenoh keys).")
    ros_render_topic: str = Field("/aoi3d/render", pattern=r"^/[A-Za-z0-9_/]+$",
                                  description="The render's topic (sensor_msgs/Image rgb8).")
    ros_camera_info_topic: str = Field("/aoi3d/camera_info", pattern=r"^/[A-Za-z0-9_/]+$",
                                       description="The render's sensor_msgs/CameraInfo.")
    ros_decision_topic: str = Field("/aoi3d/decision", pattern=r"^/[A-Za-z0-9_/]+$",
                                    description="The decision and each camera's AoI "
                                                "(diagnostic_msgs/DiagnosticArray).")
    ros_quality_topic: str = Field("/aoi3d/quality", pattern=r"^/[A-Za-z0-9_/]+$",
                                   description="Quality: PSNR at decision and display time "
                                               "(diagnostic_msgs/DiagnosticArray).")
