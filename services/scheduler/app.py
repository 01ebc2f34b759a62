"""REST API of the scheduler service: the selection policy, the AoI vector, the last decision."""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException, Request
from pydantic import BaseModel, ConfigDict, Field, StrictBool

from aoi3d.clock import SimClock
from aoi3d.policy import (
    ACCEPTED_FORMS,
    Policy,
    PolicySpecError,
    parse_policy,
    policy_from_json,
)
from aoi3d.rl.online import LearnerStatus
from services.kit.app import get_worker, include_site_routers, service_app
from services.kit.bus import Bus
from services.kit.guard import OutsideRoots, confined_path, files_in_roots
from services.scheduler.settings import Settings
from services.scheduler.worker import SchedulerWorker

DESCRIPTION = """\
Tracks the Age of Information (AoI) of every training camera from the frames the network
delivers and, every decision period, applies the selection policy to the AoI vector and
publishes a `Decision` (the frames the trainer uses).

Policies: `{"kind": "all"}`, `{"kind": "mat", "mat_ms": 51}` (use camera n iff its AoI is
below the maximum acceptable AoI Γ = mat_ms), `{"kind": "freshest", "k": 6}` (the k cameras
with the smallest AoI), `{"kind": "wait", "wait_ms": 40}` (ω-wait: the decision of epoch t
is taken at t + ω with the frames captured since t and delivered by then; the `Decision` is
stamped t + ω, the time its render is scored against), `{"kind": "ppo", "checkpoint":
"<path>", "learn": false}` (a trained single-step PPO agent's deterministic action). A new
policy is used from the next decision on. The decision step is the experiments' own
(`aoi3d.policy.decide`): a policy selects the same frames here as on the virtual clock.

With `"learn": true` the PPO policy keeps learning online: each decision samples the agent's
stochastic action, the metrics service's `Quality` for that decision is its reward, and every
`AOI3D_SCHEDULER_LEARN_BATCH_SIZE` rewarded decisions make one PPO update. The agent
(weights and optimizer state) is written to its online checkpoint (`save_to`, default
`<stem>.online.pt` next to the checkpoint) every `AOI3D_SCHEDULER_LEARN_CHECKPOINT_EVERY`
updates, when the policy is replaced and on shutdown. `GET /policy` shows the learning
state under `online`; Prometheus has the `aoi3d_ppo_*` series.
"""

Scheduler = Annotated[SchedulerWorker, Depends(get_worker)]


def _none_if_nan(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


# ---------------------------------------------------------------- /policy
class PolicyRequest(BaseModel):
    """A policy in its JSON form; the parameters depend on ``kind``."""

    model_config = ConfigDict(extra="allow")

    kind: str = Field(description="Policy kind: all, mat, freshest, wait or ppo.",
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


policy_router = APIRouter(prefix="/policy", tags=["policy"])
_READ_ONLY = {"spec", "accepted_forms", "online"}  # response fields: a GET body can be PUT back

_POLICY_EXAMPLES = {
    "mat": {"summary": "MAT with Γ = 51 ms", "value": {"kind": "mat", "mat_ms": 51}},
    "all": {"summary": "Every camera with a known AoI", "value": {"kind": "all"}},
    "freshest": {"summary": "The 6 freshest cameras", "value": {"kind": "freshest", "k": 6}},
    "wait": {"summary": "ω-wait of 40 ms (decides at t + 40 ms)",
             "value": {"kind": "wait", "wait_ms": 40}},
    "ppo": {"summary": "A trained PPO agent (deterministic)",
            "value": {"kind": "ppo", "checkpoint": "runs/ppo/quick/final.pt", "learn": False}},
    "ppo-learn": {"summary": "A PPO agent that keeps learning online",
                  "value": {"kind": "ppo", "checkpoint": "runs/ppo/quick/final.pt",
                            "learn": True}},
}


def _policy_state(worker: SchedulerWorker) -> PolicyResponse:
    policy, learner = worker.policy_and_learner()
    return PolicyResponse.of(policy, None if learner is None else learner.status())


@policy_router.get("", summary="The selection policy in force (and its online learning).",
                   response_model_exclude_none=True)
def get_policy(worker: Scheduler) -> PolicyResponse:
    return _policy_state(worker)


@policy_router.put(
    "", summary="Replace the selection policy (used from the next decision on).",
    response_model_exclude_none=True,
    responses={422: {"description": "Invalid policy (for ppo also: checkpoint or save_to "
                                    "outside AOI3D_FILES_ROOTS, checkpoint missing or "
                                    "unreadable, trained for another N, online checkpoint not "
                                    "writable); the detail says what is wrong and lists the "
                                    "accepted forms."}})
def put_policy(
    worker: Scheduler,
    request: Request,
    body: Annotated[PolicyRequest, Body(openapi_examples=_POLICY_EXAMPLES)],
) -> PolicyResponse:
    data: dict[str, Any] = body.model_dump(exclude_none=True, exclude=_READ_ONLY)
    save_to = data.pop("save_to", None)  # the scheduler's, not the policy's
    roots = request.app.state.settings.common.files_roots
    try:
        for name, value in (("checkpoint", data.get("checkpoint")), ("save_to", save_to)):
            if isinstance(value, str):
                confined_path(value, roots, name)
    except OutsideRoots as err:
        raise HTTPException(status_code=422, detail=str(err)) from None
    try:
        worker.set_policy(policy_from_json(data), save_to=save_to)
    except PolicySpecError as err:
        raise HTTPException(status_code=422, detail=str(err)) from None
    return _policy_state(worker)


class CheckpointList(BaseModel):
    """PPO checkpoints a ``PUT /policy`` of kind ppo may load."""

    checkpoints: list[str] = Field(
        description="`*.pt` files under the folders requests may name (AOI3D_FILES_ROOTS), "
                    "relative to the scheduler's working directory.",
        examples=[["models/ppo/quick/final.pt"]])


@policy_router.get("/checkpoints", summary="The PPO checkpoints a ppo policy can load.")
def get_checkpoints(request: Request) -> CheckpointList:
    roots = request.app.state.settings.common.files_roots
    return CheckpointList(checkpoints=files_in_roots(roots, "*.pt"))


# ---------------------------------------------------------------- /aoi
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


aoi_router = APIRouter(prefix="/aoi", tags=["aoi"])


@aoi_router.get("", summary="The current AoI vector (null = unknown).")
def get_aoi(worker: Scheduler) -> AoIResponse:
    snap = worker.aoi()
    return AoIResponse(time_ms=snap.time_ms, camera_ids=list(snap.camera_ids),
                       aoi_ms=[_none_if_nan(a) for a in snap.aoi_ms],
                       newest_ms=[_none_if_nan(u) for u in snap.newest_ms])


# ---------------------------------------------------------------- /decision
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


decision_router = APIRouter(prefix="/decision", tags=["decision"])


@decision_router.get("", summary="The latest decision.",
                     responses={404: {"description": "No decision was taken yet."}})
def get_decision(worker: Scheduler) -> DecisionResponse:
    msg = worker.last_decision
    if msg is None:
        raise HTTPException(status_code=404, detail="no decision was taken yet; the first comes "
                                                    "at the next decision epoch")
    return DecisionResponse(
        decision_id=msg.decision_id, time_ms=msg.time_ms, camera_ids=list(msg.camera_ids),
        aoi_ms=[_none_if_nan(a) for a in msg.aoi_ms],
        selected=[FrameRefModel(camera_id=r.camera_id, sequence=r.sequence,
                                generation_ms=r.generation_ms, aoi_ms=r.aoi_ms)
                  for r in msg.selected],
        policy=msg.policy)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None) -> FastAPI:
    """The scheduler service; ``bus``/``clock`` default to Zenoh and the shared clock."""
    settings = settings or Settings()
    common = settings.common
    clock = clock or SimClock(epoch_s=common.epoch_s, time_scale=common.time_scale)
    policy = parse_policy(settings.policy).on_device(settings.device)
    policy.check_fits(common.cameras)  # fail at start-up, not at the first decision

    def build_worker(the_bus: Bus, registry, site: str) -> SchedulerWorker:
        return SchedulerWorker(the_bus, registry, run_id=common.run_id, site=site,
                               n_cameras=common.cameras, clock=clock, policy=policy,
                               decision_period_ms=settings.decision_period_ms,
                               inbox_size=settings.inbox_size,
                               learn=settings.learn_config(), device=settings.device,
                               stall_s=common.stall_s)

    app = service_app(title="aoi3d scheduler", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus, per_site=True)
    include_site_routers(app, policy_router, aoi_router, decision_router)
    return app
