"""Settings of the ingest service (environment prefix ``AOI3D_INGEST_``); the rig file itself
is the run's (``AOI3D_RIG``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.kit.settings import ServiceSettings


class Settings(ServiceSettings):
    """Real cameras in: ROS 2 images (rmw_zenoh or zenoh-bridge-ros2dds keys) with their poses
    and intrinsics, as the pipeline's frames."""

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
