"""Settings of the console service (environment prefix ``AOI3D_CONSOLE_``)."""

from __future__ import annotations

import os

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from services.kit.ports import SERVICE_PORTS
from services.kit.settings import ServiceSettings

UPSTREAMS = {name: SERVICE_PORTS[name]
             for name in ("camera", "network", "scheduler", "dispatcher", "metrics")}
"""The services the console shows, polls and controls, with their default ports: the five of
the pipeline (not the recorder, which compose and Kubernetes do not run)."""


def _default_upstream() -> dict[str, str]:
    """Each service on 127.0.0.1 at the port ``aoi3d up`` gave it (AOI3D_<NAME>_PORT)."""
    return {name: f"http://127.0.0.1:{os.environ.get(f'AOI3D_{name.upper()}_PORT', port)}"
            for name, port in UPSTREAMS.items()}


class Settings(ServiceSettings):
    """The console: a web page with the novel view beside the truth, the AoI per camera, the
    quality over time and the controls; it calls the services' REST APIs server-side."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_CONSOLE_", extra="ignore")

    port: int = Field(SERVICE_PORTS["console"], ge=0, le=65535,
                      description="REST API and web page port.")
    upstream: dict[str, str] = Field(
        default_factory=_default_upstream,
        json_schema_extra={"doc_default": "`http://127.0.0.1:<AOI3D_<NAME>_PORT>` each"},
        description="Base URL of each service the console calls (JSON object); default: "
                    "127.0.0.1 at the ports `aoi3d up` gave them (AOI3D_<NAME>_PORT).")
    push_period_s: float = Field(0.5, gt=0.05, le=10,
                                 description="Seconds between two updates pushed to the page.")
    poll_period_s: float = Field(1.0, gt=0.1, le=60,
                                 description="Seconds between two polls of the services' "
                                             "status (channel, dispatcher, policy).")
    viewer_port: int = Field(
        default_factory=lambda: int(os.environ.get("AOI3D_VIEWER_PORT",
                                                   SERVICE_PORTS["viewer"])),
        ge=1, le=65535, json_schema_extra={"doc_default": "AOI3D_VIEWER_PORT, else 8108"},
        description="Port of the 3D viewer the page links to, on the page's own host.")
    history_s: float = Field(300.0, gt=10, le=3600,
                             description="Wall seconds of quality timeline the page keeps.")

    @field_validator("upstream")
    @classmethod
    def _all_services(cls, value: dict[str, str]) -> dict[str, str]:
        missing = sorted(set(UPSTREAMS) - set(value))
        if missing:
            raise ValueError(f"upstream lacks {', '.join(missing)}")
        return {k: v.rstrip("/") for k, v in value.items()}
