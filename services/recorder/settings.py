"""Settings of the recorder service (environment prefix ``AOI3D_RECORDER_``)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from services.kit.settings import ServiceSettings


class Settings(ServiceSettings):
    """The run's recorder: the bus's frames, decisions, renders, quality and outcomes into an
    MCAP file (docs/recording.md)."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_RECORDER_", extra="ignore")

    port: int = Field(8107, ge=0, le=65535, description="REST API port.")
    path: Path | None = Field(
        None, description="Record into this MCAP file from the start (`aoi3d up --record "
                          "PATH` sets it); unset: idle until `POST /recording/start`.")
    max_bytes: int = Field(
        0, ge=0, description="Size cap of one MCAP segment in bytes (0: none); a full segment "
                             "is finished and the recording goes on in <stem>.part2.mcap, "
                             "part3 … beside it (nothing is deleted: a full disk stops it, "
                             "every file whole).")
    chunk_bytes: int = Field(1 << 20, ge=4096, le=64 << 20,
                             description="MCAP chunk size (compressed as a unit).")
    compression: Literal["zstd", "lz4", "none"] = Field(
        "zstd", description="Chunk compression.")
    inbox_size: int = Field(
        4096, ge=1, description="Bus messages buffered between the bus and the writing "
                                "thread (the oldest dropped and counted beyond).")

    @field_validator("path", mode="before")
    @classmethod
    def _unset(cls, v: object) -> object:
        """An empty value is unset (compose passes ``${AOI3D_RECORDER_PATH:-}``), not ``.``."""
        return None if isinstance(v, str) and not v.strip() else v
