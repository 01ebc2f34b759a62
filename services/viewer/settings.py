"""Settings of the 3D viewer (environment prefix ``AOI3D_VIEWER_``)."""

from __future__ import annotations

import os

from pydantic import AliasChoices, Field
from pydantic_settings import SettingsConfigDict

from services.kit.ports import SERVICE_PORTS
from services.kit.settings import ServiceSettings


def _url(service: str) -> str:
    port = os.environ.get(f"AOI3D_{service.upper()}_PORT", SERVICE_PORTS[service])
    return f"http://127.0.0.1:{port}"


class Settings(ServiceSettings):
    """The 3D viewer: the scene box, every camera as a frustum coloured by its AoI at the
    decision in force (the cameras it used marked, its latest delivered frame as the image),
    the truth camera, and the live reconstruction seen from the viewer's own camera (a free
    view the dispatcher's pool renders as the user orbits); controls for the policy and Γ."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_VIEWER_", extra="ignore")

    port: int = Field(SERVICE_PORTS["viewer"], ge=0, le=65535,
                      description="The viewer's web page, its websocket and REST API port.")
    dispatcher_url: str = Field(
        default_factory=lambda: _url("dispatcher"),
        validation_alias=AliasChoices("AOI3D_VIEWER_DISPATCHER_URL", "dispatcher_url",
                                      "AOI3D_VIEWER_TRAINER_URL"),  # its old name, one release
        json_schema_extra={"doc_default": "`http://127.0.0.1:<AOI3D_DISPATCHER_PORT>`"},
        description="The dispatcher's REST API: free views (GET /render.png?c2w=…).")
    scheduler_url: str = Field(
        default_factory=lambda: _url("scheduler"),
        json_schema_extra={"doc_default": "`http://127.0.0.1:<AOI3D_SCHEDULER_PORT>`"},
        description="The scheduler's REST API: the policy and Γ controls (PUT /policy).")
    render_height: int = Field(
        240, ge=32, le=1024,
        description="Height in pixels of the free views behind the viewer's scene (the width "
                    "follows the browser's aspect).")
    refresh_s: float = Field(
        2.0, gt=0.1, le=60,
        description="Seconds between two free views of an unmoved viewer camera (the live "
                    "reconstruction updates as new decisions are rendered).")
    update_period_s: float = Field(
        1.0, gt=0.05, le=60, description="Seconds between two redraws of the cameras.")
    thumbnails: bool = Field(
        True, description="Show each camera's latest delivered frame on its frustum.")
