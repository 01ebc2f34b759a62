"""Settings of a reconstruction worker (environment prefix ``AOI3D_RECON_``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.kit.settings import CommonSettings


class Settings(BaseSettings):
    """A reconstruction worker of the pool: asks the dispatcher service for jobs, reconstructs
    each decision it is given and publishes the render. No REST API: it is seen in the dispatcher
    service's `GET /workers` (membership by Zenoh liveliness)."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_RECON_", extra="ignore")

    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Torch device: auto (CUDA when available, else CPU), cpu or cuda.")
    torch_threads: int = Field(
        1, ge=0, le=256,
        description="Torch CPU threads of this worker (0: torch's default). 1 by default: "
                    "the grid's fused kernels run on one thread whatever this says (measured "
                    "on 2 cores: 0.42-0.55 s per reconstruction on 1 thread and on 2); with "
                    "the torch code, 1.38 s on 1 thread against 1.71 s on 2, and two 1-thread "
                    "workers side by side 1.30-1.37 s each; add workers, not threads.")
    max_wait_s: float = Field(
        2.0, gt=0, le=60,
        description="How long the dispatcher may hold this worker's request for work when no "
                    "decision is pending (a long poll: the next decision goes to a waiting "
                    "worker at once).")
    query_margin_s: float = Field(
        5.0, gt=0, le=120,
        description="Wall seconds a request may take beyond max_wait_s before the worker "
                    "gives up on it and asks again (the busy-machine allowance).")
    background_steps: int = Field(
        10, ge=1, le=10_000,
        description="With the warm or fork carry: training steps of this worker's own model "
                    "between two requests while no job is pending.")
    worker_id: str | None = Field(
        None, pattern=r"^[A-Za-z0-9_.\-]{1,64}$",
        description="This worker's id in the pool (its liveliness token's last chunk). "
                    "Default: <host>-<pid>-<4 random hex>, new at every start.")
    common: CommonSettings = Field(default_factory=CommonSettings)
