"""Settings of the trainer service (environment prefix ``AOI3D_TRAINER_``).

The radiance-field backend is chosen by name from ``aoi3d.field.BACKENDS``, the one place
that maps a backend name to its config; ``PUT /backend`` switches it at run time.
"""

from __future__ import annotations

from pathlib import Path
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
        0.5, gt=0, le=3600,
        description="Wall seconds of background training between the end of one render of "
                    "the held-out camera and the start of the next.")
    carry: Literal["fork", "fresh", "warm"] = Field(
        "fresh",
        description="How a render is made (aoi3d.field.carry, the experiments' carry modes): "
                    "fresh = the paper's per-time reconstruction, a new model trains "
                    "render_steps steps on the rendered decision's frames alone; fork = a copy "
                    "of the continuously trained model does; warm = the continuously trained "
                    "model renders as it is. `PUT /carry` changes it at run time.")
    render_steps: int = Field(
        100, ge=1, le=100_000,
        description="Training steps spent on a rendered decision's own frames (fork, fresh).")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Torch device: auto (CUDA when available, else CPU), cpu or cuda.")
    torch_threads: int = Field(
        0, ge=0, le=256,
        description="Torch CPU threads of this process (the field config's num_threads); "
                    "0 keeps torch's default.")
    seed: int = Field(0, ge=0, description="Seed of the field's initialisation and ray sampling.")
    checkpoint_dir: Path = Field(
        Path("runs/checkpoints"),
        description="Folder of the model checkpoint, <run id>.trainer.pt, written atomically "
                    "every checkpoint_period_s while the model trains; a restarted trainer "
                    "resumes from it when backend and scene match. POST /reset and PUT "
                    "/backend delete it (they start fresh).")
    checkpoint_period_s: float = Field(
        30.0, ge=0, le=86_400,
        description="Wall seconds between two checkpoint writes (0: no checkpoints).")
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
