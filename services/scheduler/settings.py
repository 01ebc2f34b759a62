"""Settings of the scheduler service (environment prefix ``AOI3D_SCHEDULER_``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from aoi3d.policy import parse_policy
from aoi3d.rl.online import LearnConfig
from services.kit.ports import SERVICE_PORTS
from services.kit.settings import ServiceSettings


class Settings(ServiceSettings):
    """The scheduler: tracks each camera's AoI and decides which frames the dispatcher uses."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_SCHEDULER_", extra="ignore")

    port: int = Field(SERVICE_PORTS["scheduler"], ge=0, le=65535, description="REST API port.")
    decision_period_ms: float = Field(
        30.0, gt=0, le=60_000, allow_inf_nan=False,
        description="Sim ms between two decisions; decisions are taken at t = k·period.")
    policy: str = Field(
        "mat:70", description="Initial selection policy spec: all | mat:<mat_ms> | "
                              "freshest:<k> | wait:<ms> | ppo:<checkpoint> (deterministic, not "
                              "learning; `PUT /policy` with learn=true learns online) | "
                              "adaptive:plugin | adaptive:bandit (a Γ that follows the "
                              "channel). mat:70 "
                              "is the live optimum on the default scene (docs/research.md, "
                              "'The tradeoff, live').",
        examples=["mat:70", "all", "freshest:6", "ppo:models/ppo/quick/final.pt"])
    inbox_size: int = Field(
        1024, ge=1, le=100_000,
        description="Delivered frames queued between the bus and the decision thread "
                    "(oldest dropped when full).")
    learn_batch_size: int = Field(
        8, ge=1, le=4096,
        description="Online PPO (a ppo policy with learn=true): rewarded decisions per PPO "
                    "update.")
    learn_reward_timeout_s: float = Field(
        10.0, gt=0, le=86_400, allow_inf_nan=False,
        description="Online PPO: wall seconds a decision waits for its Quality reward before "
                    "it expires (counted in aoi3d_ppo_rewards_expired_total).")
    learn_checkpoint_every: int = Field(
        10, ge=1, le=1_000_000,
        description="Online PPO: updates between two writes of the online checkpoint (also "
                    "written when learning stops and on shutdown).")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "cpu", description="Torch device of a ppo policy's agent: cpu, cuda, or auto (CUDA "
                           "when available). The network is tiny (one small forward pass per "
                           "decision), hence cpu by default.")
    torch_threads: int = Field(
        1, ge=0, le=256,
        description="Torch CPU threads of this process (ppo policies); 0 keeps torch's "
                    "default.")

    step_ms: float = Field(
        3.4, ge=0, le=60_000, allow_inf_nan=False,
        description="Wall ms per training step of the pool: the slope of the lag model "
                    "(decision → display) until renders of two budgets teach it its own; "
                    "what compute-aware policies (dmat, deadline) read, with the queue and "
                    "fixed cost learned from the renders (aoi3d.policy.budget.LagEstimator).")

    @field_validator("policy")
    @classmethod
    def _valid_policy(cls, value: str) -> str:
        return parse_policy(value).spec  # PolicySpecError (a ValueError) lists accepted forms

    def learn_config(self) -> LearnConfig:
        """The online-learning settings as the learner's :class:`LearnConfig`."""
        return LearnConfig(batch_size=self.learn_batch_size,
                           reward_timeout_s=self.learn_reward_timeout_s,
                           checkpoint_every=self.learn_checkpoint_every)
