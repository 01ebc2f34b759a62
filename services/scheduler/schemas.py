"""The scheduler's REST schemas: request and response bodies of /policy, /aoi and /decision."""

from __future__ import annotations

import dataclasses
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictInt

from aoi3d.policy import ACCEPTED_FORMS, BUDGET_MAX_STEPS, Policy
from aoi3d.rl.online import LearnerStatus


class PolicyRequest(BaseModel):
    """A policy in its JSON form; the parameters depend on ``kind``."""

    model_config = ConfigDict(extra="allow")

    kind: str = Field(description="Policy kind: all, mat, freshest, wait, ppo, adaptive, or "
                                  "the compute-aware dmat and deadline.",
                      examples=["mat"])
    mat_ms: float | None = Field(
        None, description="kind mat: the maximum acceptable AoI Γ in ms (finite, >= 0); "
                          "camera n is used iff its AoI < mat_ms. 0 selects no camera.",
        examples=[51])
    k: int | None = Field(
        None, description="kind freshest: how many cameras (those with the smallest AoI) to "
                          "use, 0..N.", examples=[6])
    wait_ms: int | None = Field(
        None, description="kind wait: ω in whole ms (>= 0); the decision of epoch t is taken "
                          "at t + ω and uses camera n iff its AoI then is <= ω (a frame "
                          "captured since t). 0 selects no camera.", examples=[40])
    checkpoint: str | None = Field(
        None, description="kind ppo: path of a PPO checkpoint (aoi3d ppo train), as the scheduler "
                          "process sees it; trained for N cameras.",
        examples=["runs/ppo/quick/final.pt"])
    learn: StrictBool | None = Field(
        None, description="kind ppo: keep learning online from the rewards of the decisions "
                          "(default false: the deterministic action, nothing learned).",
        examples=[False])
    budget_steps: StrictInt | None = Field(
        None, ge=1, le=BUDGET_MAX_STEPS,
        description="Any kind but deadline: the decision's training budget, the steps its "
                    "reconstruction takes (the spec's '@<steps>', e.g. mat:70@50); absent: "
                    "the pool's render_steps (PUT /carry on the dispatcher).", examples=[50])
    deadline_ms: float | None = Field(
        None, description="kind deadline: the budget is the largest whose render is on screen "
                          "within deadline_ms of its decision (queue + compute, as learned "
                          "from the renders).", examples=[100])
    save_to: str | None = Field(
        None, description="kind ppo with learn: file the online checkpoint is written to "
                          "(default <checkpoint stem>.online.pt next to the checkpoint; the "
                          "source is overwritten only when named here).",
        examples=["runs/ppo/live.online.pt"])
    spec: str | None = Field(None, description="Read-only (responses); ignored in requests.")
    accepted_forms: list[str] | None = Field(
        None, description="Read-only (responses); ignored in requests.")
    online: dict[str, Any] | None = Field(
        None, description="Read-only (responses); ignored in requests.")


class OnlineStatus(BaseModel):
    """Online learning of a ppo policy with learn=true (since it was put)."""

    save_to: str = Field(description="Where the online checkpoint is written.",
                         examples=["runs/ppo/final.online.pt"])
    batch_size: int = Field(description="Rewarded decisions per update.", examples=[8])
    episodes_learned: int = Field(description="Decisions whose reward went into an update.",
                                  examples=[64])
    agent_episodes: int = Field(
        description="Episodes the agent has learned in all, its checkpoint's included.",
        examples=[4864])
    updates: int = Field(description="PPO updates made.", examples=[8])
    pending_rewards: int = Field(description="Decisions waiting for their reward.",
                                 examples=[3])
    batch_filled: int = Field(description="Rewarded decisions waiting for the next update.",
                              examples=[5])
    expired: int = Field(description="Decisions whose reward did not come in time.",
                         examples=[0])
    unscored: int = Field(description="Decisions no render represented (a later decision's "
                                      "reward came first).", examples=[410])
    ignored: dict[str, int] = Field(description="Quality messages not used, by reason.",
                                    examples=[{"unknown": 2}])
    mean_reward: float | None = Field(description="Mean reward of the latest update's batch.",
                                      examples=[0.71])
    entropy: float | None = Field(description="Policy entropy (nats) at the latest decision.",
                                  examples=[9.8])
    last_update: dict[str, float] | None = Field(
        description="Statistics of the latest update (losses, entropy, approx_kl, clip_frac, "
                    "mean_reward).")
    checkpoints_saved: int = Field(description="Online checkpoints written.", examples=[0])
    last_saved_s: float | None = Field(description="Unix time of the latest write.",
                                       examples=[None])

    @classmethod
    def of(cls, status: LearnerStatus) -> OnlineStatus:
        return cls(**dataclasses.asdict(status))


class PolicyResponse(BaseModel):
    """The policy in force (or from the next decision on, after a PUT)."""

    model_config = ConfigDict(extra="allow")

    kind: str = Field(description="Policy kind.", examples=["mat"])
    mat_ms: float | None = Field(None, description="kind mat: Γ in ms.", examples=[51])
    k: int | None = Field(None, description="kind freshest: cameras used.", examples=[None])
    wait_ms: int | None = Field(None, description="kind wait: ω in ms.", examples=[None])
    checkpoint: str | None = Field(None, description="kind ppo: the checkpoint loaded.",
                                   examples=[None])
    learn: bool | None = Field(None, description="kind ppo: learning online.", examples=[None])
    budget_steps: int | None = Field(None, description="The decision's training budget; null: "
                                     "the pool's render_steps.", examples=[50])
    deadline_ms: float | None = Field(None, description="kind deadline: its deadline (ms).",
                                      examples=[None])
    save_to: str | None = Field(None, description="kind ppo, learning: the online checkpoint.",
                                examples=[None])
    spec: str = Field(description="The policy's text spec (as in the Decision messages).",
                      examples=["mat:51"])
    accepted_forms: list[str] = Field(
        description="Text forms of every known policy kind.",
        examples=[["all", "mat:<ms>", "freshest:<k>", "wait:<ms>", "ppo:<checkpoint>"]])
    online: OnlineStatus | None = Field(None, description="kind ppo, learning: its state.")

    @classmethod
    def of(cls, policy: Policy, status: LearnerStatus | None = None) -> PolicyResponse:
        online = None if status is None else OnlineStatus.of(status)
        return cls(**policy.to_json(), spec=policy.spec, accepted_forms=list(ACCEPTED_FORMS),
                   save_to=None if status is None else status.save_to, online=online)


class CheckpointList(BaseModel):
    """PPO checkpoints a ``PUT /policy`` of kind ppo may load."""

    checkpoints: list[str] = Field(
        description="`*.pt` files under the folders requests may name (AOI3D_FILES_ROOTS), "
                    "relative to the scheduler's working directory.",
        examples=[["models/ppo/quick/final.pt"]])


class AoIResponse(BaseModel):
    """The AoI vector now, from the frames delivered so far."""

    time_ms: float = Field(description="Sim time t of the vector (now).", examples=[12030.0])
    camera_ids: list[int] = Field(description="Training cameras, in vector order.",
                                  examples=[[1, 2, 3]])
    aoi_ms: list[float | None] = Field(
        description="AoI t − U_n per camera in ms; null where no frame was delivered yet.",
        examples=[[41.0, None, 95.0]])
    newest_ms: list[float | None] = Field(
        description="Generation time U_n of each camera's newest delivered frame; null if none.",
        examples=[[11989.0, None, 11935.0]])


class FrameRefModel(BaseModel):
    camera_id: int = Field(description="Camera of the selected frame.", examples=[3])
    sequence: int = Field(description="The frame's per-camera sequence number.", examples=[401])
    generation_ms: float = Field(description="The frame's generation time U_n.",
                                 examples=[12000.0])
    aoi_ms: float = Field(description="Its AoI at the decision time.", examples=[30.0])


class DecisionResponse(BaseModel):
    """The latest published decision."""

    decision_id: int = Field(description="Increasing id of the decision.", examples=[401])
    time_ms: float = Field(
        description="Time the selection is for (sim ms): the decision epoch t, or t + ω for "
                    "a wait policy; the AoI is taken, and the render scored, at this time.",
        examples=[12030.0])
    camera_ids: list[int] = Field(description="Cameras of the AoI vector.", examples=[[1, 2, 3]])
    aoi_ms: list[float | None] = Field(description="AoI at time_ms per camera; null = unknown.",
                                       examples=[[30.0, None, 95.0]])
    selected: list[FrameRefModel] = Field(description="Frames chosen for training.")
    policy: str = Field(description="Spec of the policy that decided.", examples=["mat:51"])
    gamma_ms: float | None = Field(
        default=None, description="Γ of the MAT rule the policy applied: an adaptive "
        "policy's Γ in force (it follows the channel); null for a policy without one.",
        examples=[100.0])
    budget_steps: int | None = Field(
        default=None, description="The decision's training budget (steps); null: the pool's "
        "render_steps.", examples=[50])
    expected_lag_ms: float | None = Field(
        default=None, description="The scheduler's expected lag from the decision to its "
        "display (sim ms), learned from the scored renders; null before any.",
        examples=[35.6])
