"""Settings of the camera service (environment prefix ``AOI3D_CAMERA_``)."""

from __future__ import annotations

import json
from typing import Annotated

from pydantic import Field, field_validator
from pydantic_settings import NoDecode, SettingsConfigDict

from services.kit.ports import SERVICE_PORTS
from services.kit.settings import ServiceSettings

CameraIds = Annotated[list[int], NoDecode]


def _split_ids(value: object) -> object:
    """Accept a JSON list (``[1,2,3]``) or a comma-separated string (``1,2,3``)."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            return json.loads(text)
        return [int(part) for part in text.split(",") if part.strip()]
    return value


class Settings(ServiceSettings):
    """The camera rig's service: generation period and which training cameras stream."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_CAMERA_", extra="ignore")

    port: int = Field(SERVICE_PORTS["camera"], ge=0, le=65535, description="REST API port.")
    period_ms: float = Field(30.0, ge=1.0, le=60_000,
                             description="Generation period C in sim ms: frames at t = k·C.")
    paused: bool = Field(False, description="Start with frame generation paused.")
    active_cameras: CameraIds = Field(
        default_factory=list,
        description="Training camera ids that stream (comma-separated or JSON list); "
                    "empty = all of 1..N.")

    _split = field_validator("active_cameras", mode="before")(
        classmethod(lambda cls, v: _split_ids(v)))
