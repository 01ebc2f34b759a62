"""Settings of the dispatcher service (environment prefix ``AOI3D_DISPATCHER_``; the old
``AOI3D_TRAINER_`` names, from when the service was called the trainer, are read too for one
release, the new name winning, and each one set is named in a deprecation line at start).

The radiance-field backend is chosen by name from ``aoi3d.field.BACKENDS``, the one place
that maps a backend name to its config; ``PUT /backend`` switches it at run time.
"""

from __future__ import annotations

from pydantic import Field, field_validator
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from aoi3d.field import check_backend
from aoi3d.field.carry import CarryMode
from services.kit.ports import SERVICE_PORTS
from services.kit.settings import ServiceSettings

OLD_PREFIX = "AOI3D_TRAINER_"
"""The settings' prefix before the service was renamed (read as an alias for one release)."""


class Settings(ServiceSettings):
    """The pool's dispatcher. It takes the scheduler's decisions and hands each to
    one reconstruction worker (`python -m services.recon`) with the frames it selected; the
    worker trains a radiance field on them and renders the novel view."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_DISPATCHER_", extra="ignore")

    port: int = Field(SERVICE_PORTS["dispatcher"], ge=0, le=65535, description="REST API port.")
    backend: str = Field("grid", description="Radiance-field backend at start, a name in "
                                             "aoi3d.field.BACKENDS (`aoi3d field backends` "
                                             "lists them); `PUT /backend` switches it at run "
                                             "time.",
                         examples=["grid"])
    carry: CarryMode = Field(
        "stream",
        description="How a render is made (aoi3d.field.carry, the experiments' carry modes): "
                    "fresh = the paper's per-time reconstruction, a new model trains "
                    "render_steps steps on the rendered decision's frames alone; stream = the "
                    "streaming warm start, each worker trains its previous decision's model "
                    "render_steps more steps on the new frames (a cold start, or a model more "
                    "than warm_max_gap_ms of scene time old: cold_steps); fork = a copy "
                    "of the worker's continuously trained model does; warm = that model renders "
                    "as it is (fork and warm: one model per worker, carried from job to job). "
                    "`PUT /carry` changes it at run time. The default, stream with 25 steps, "
                    "is what a viewer sees best: run back to back by `aoi3d up --time-scale "
                    "0.3` on 2 cores it had 100 % of the decisions scored, shown a median 21 "
                    "sim ms after them at 26.0 dB, where fresh with 100 steps had 77 %, 87 ms, "
                    "22.8 dB (docs/performance.md, \"The live default\").")
    render_steps: int = Field(
        25, ge=1, le=100_000,
        description="Training steps spent on a rendered decision's own frames (fork, fresh; "
                    "stream: a warm start's), unless the decision names its own budget (a "
                    "policy's `@steps`). 25 goes with the stream carry (a warm start of 25 "
                    "steps beats a fresh model of 100 on the rotor at a quarter of the "
                    "compute); with carry fresh set 100.")
    cold_steps: int = Field(
        100, ge=1, le=100_000,
        description="stream: the budget of a cold start (a worker's first job, or one after "
                    "a model too old).")
    warm_max_gap_ms: float = Field(
        500.0, ge=0, le=3_600_000,
        description="stream: a worker whose last decision is further than this from the new "
                    "one, in scene ms, starts cold (its model is too old to start from). "
                    "Measured on the rotor: 90 ms apart a warm start is 1.9 dB worse than a "
                    "fresh one at its decision time, but live it is shown so much sooner "
                    "that it wins at display time; a limit below a cold job's own duration "
                    "(135 sim ms at time scale 0.3) never lets a pool warm up.")
    seed: int = Field(0, ge=0, description="Seed of the field's initialisation and ray sampling "
                                           "(carried by every job).")
    job_timeout_s: float = Field(
        120.0, gt=0, le=86_400,
        description="Wall seconds a worker may hold a decision before it is counted lost "
                    "(timeout): a stopped or cut-off worker never leaves a decision open.")
    fresh_fraction: float = Field(
        0.5, ge=0, le=1,
        description="Wait for the next decision: a worker that asks when the pending decision "
                    "has waited longer than this fraction of the decision period waits for "
                    "the next one instead (due within the rest of the period), and the stale "
                    "one is superseded; 1 = never wait (take the pending one at once). At "
                    "time scale 1 with two workers on 2 cores, 0.5 cut the pool wait from 13 "
                    "to 3 ms and the median display lag by 8-26 ms at the same renders/s "
                    "(docs/measurements.md, \"Real time on two cores\").")
    window_s: float = Field(
        30.0, gt=0, le=3600,
        description="Wall seconds over which the pool's rates, rendered fraction, waits and "
                    "busy fractions are measured (GET /workers, /metrics).")
    frames_per_camera: int = Field(
        8, ge=1, le=1024,
        description="Delivered frames kept per camera (encoded) to resolve a decision's "
                    "selection.")

    view_rate_per_s: float = Field(
        4.0, gt=0, le=1000,
        description="Free views and exports (GET /render.png?c2w=…, GET /export.ply, the 3D "
                    "viewer) per second, on average, over the whole run; beyond it 429 (counted "
                    "in aoi3d_dispatcher_views_total{outcome=\"rate_limited\"}). They are never "
                    "scored and never delay a decision's render (the worker answers them from "
                    "a snapshot, on a thread of their own).")
    view_burst: int = Field(8, ge=1, le=1000,
                            description="Free views and exports allowed back to back.")
    max_view_side: int = Field(1024, ge=8, le=4096,
                               description="Largest width or height of a free view (pixels).")
    view_timeout_s: float = Field(
        20.0, gt=0, le=600, description="Wall seconds to wait for a worker's free view.")
    export_timeout_s: float = Field(
        120.0, gt=0, le=3600, description="Wall seconds to wait for a worker's export.")

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings],
                                   init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource,
                                   dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        """The new names first, then the old ``AOI3D_TRAINER_`` ones (for one release)."""
        old = EnvSettingsSource(settings_cls, env_prefix=OLD_PREFIX)
        return init_settings, env_settings, old, dotenv_settings, file_secret_settings

    @field_validator("backend")
    @classmethod
    def _known_backend(cls, value: str) -> str:
        return check_backend(value)
