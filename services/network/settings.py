"""Settings of the network service (environment prefix ``AOI3D_NETWORK_``)."""

from __future__ import annotations

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from aoi3d.channel import parse_channel
from aoi3d.channel.varying import check_frame_encoding
from services.kit.ports import SERVICE_PORTS
from services.kit.settings import ServiceSettings


class Settings(ServiceSettings):
    """The camera uplinks: one D/G/1/0 link per training camera."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_NETWORK_", extra="ignore")

    port: int = Field(SERVICE_PORTS["network"], ge=0, le=65535, description="REST API port.")
    delay: str = Field("exp:60", description="Delay spec of every link (ms): exp:MEAN, const:D, "
                                             "uniform:LO:HI, gamma:K:THETA or "
                                             "lognormal:MU:SIGMA; or a channel that changes: "
                                             "regimes:SPEC@DUR,…, "
                                             "trace:PATH[,offset=MS][,spread=MS][,scale=S], "
                                             "cell:PATH[,…].")
    per_camera: dict[int, str] = Field(
        default_factory=dict,
        description='Per-camera delay overrides as a JSON object, e.g. {"3": "const:40"}.')
    seed: int = Field(1, ge=0, description="Seed of the links' random streams "
                                           "(one independent stream per camera).")
    frame_encoding: str = Field(
        "png", description="How a frame's size is counted on a trace or cell channel: png "
                           "(the bytes the camera sent) or jpeg:Q (the frame re-encoded as "
                           "JPEG at quality Q, 1–95, for its size only; the edge still gets "
                           "the PNG).")
    inbox_size: int = Field(1024, ge=1, description="Offered frames buffered between the bus "
                                                    "and the link thread (oldest dropped).")

    @field_validator("delay")
    @classmethod
    def _canonical_delay(cls, value: str) -> str:
        return parse_channel(value).spec

    @field_validator("frame_encoding")
    @classmethod
    def _known_encoding(cls, value: str) -> str:
        check_frame_encoding(value)
        return value

    @field_validator("per_camera")
    @classmethod
    def _canonical_per_camera(cls, value: dict[int, str]) -> dict[int, str]:
        return {int(n): parse_channel(spec).spec for n, spec in value.items()}
