"""Settings of the trainer service (environment prefix ``AOI3D_TRAINER_``).

The radiance-field backend is chosen by name from ``aoi3d.field.BACKENDS``, the one place
that maps a backend name to its config; ``PUT /backend`` switches it at run time.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from aoi3d.field import BACKENDS
from services.kit.settings import ServiceSettings


class Settings(ServiceSettings):
    """The trainer: trains a radiance field on the decided frames and renders the novel view."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_TRAINER_", extra="ignore")

    port: int = Field(8104, ge=0, le=65535, description="REST API port.")
    backend: str = Field("grid", description="Radiance-field backend at start, a name in "
                                             "aoi3d.field.BACKENDS (`aoi3d field backends` "
                                             "lists them); `PUT /backend` switches it at run "
                                             "time.",
                         examples=["grid"])
    steps_per_chunk: int = Field(
        1, ge=1, le=10_000,
        description="Training steps between two checks for a new decision. Small keeps the "
                    "trainer responsive (decisions come every 0.3 wall s at time_scale 0.1; a "
                    "default grid step on 2 CPU cores takes ~30 ms); the per-chunk overhead is "
                    "microseconds.")
    render_period_s: float = Field(
        2.0, gt=0, le=3600,
        description="Wall seconds between two renders of the held-out camera.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Torch device: auto (CUDA when available, else CPU), cpu or cuda.")
    torch_threads: int = Field(
        0, ge=0, le=256,
        description="Torch CPU threads of this process (the field config's num_threads); "
                    "0 keeps torch's default.")
    seed: int = Field(0, ge=0, description="Seed of the field's initialisation and ray sampling.")
    frames_per_camera: int = Field(
        8, ge=1, le=1024,
        description="Delivered frames kept per camera (encoded) to resolve a decision's "
                    "selection.")

    @field_validator("backend")
    @classmethod
    def _known_backend(cls, value: str) -> str:
        if value not in BACKENDS:
            raise ValueError(
                f"unknown backend {value!r}; available: {', '.join(sorted(BACKENDS))}")
        return value
