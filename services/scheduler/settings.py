"""Settings of the scheduler service (environment prefix ``AOI3D_SCHEDULER_``)."""

from __future__ import annotations

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from aoi3d.policy import parse_policy
from services.kit.settings import ServiceSettings


class Settings(ServiceSettings):
    """The scheduler: tracks each camera's AoI and decides which frames the trainer uses."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_SCHEDULER_", extra="ignore")

    port: int = Field(8103, ge=0, le=65535, description="REST API port.")
    decision_period_ms: float = Field(
        30.0, gt=0, le=60_000, allow_inf_nan=False,
        description="Sim ms between two decisions; decisions are taken at t = k·period.")
    policy: str = Field(
        "mat:51", description="Initial selection policy spec: all | mat:<mat_ms> | freshest:<k>.",
        examples=["mat:51", "all", "freshest:6"])
    inbox_size: int = Field(
        1024, ge=1, le=100_000,
        description="Delivered frames queued between the bus and the decision thread "
                    "(oldest dropped when full).")

    @field_validator("policy")
    @classmethod
    def _valid_policy(cls, value: str) -> str:
        return parse_policy(value).spec  # PolicySpecError (a ValueError) lists accepted forms
