"""REST API of the scheduler service: the selection policy, the AoI vector, the last decision."""

from __future__ import annotations

import math
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException, Request

from aoi3d.clock import SimClock
from aoi3d.policy import (
    PolicySpecError,
    parse_policy,
    policy_from_json,
)
from services.kit.app import get_worker, include_site_routers, service_app
from services.kit.bus import Bus
from services.kit.guard import OutsideRoots, confined_path, files_in_roots
from services.scheduler.runtime import SchedulerRuntime
from services.scheduler.schemas import (
    AoIResponse,
    CheckpointList,
    DecisionResponse,
    FrameRefModel,
    PolicyRequest,
    PolicyResponse,
)
from services.scheduler.settings import Settings

DESCRIPTION = """\
Tracks the Age of Information (AoI) of every training camera from the frames the network
delivers and, every decision period, applies the selection policy to the AoI vector and
publishes a `Decision` (the frames the dispatcher uses).

Policies: `{"kind": "all"}`, `{"kind": "mat", "mat_ms": 51}` (use camera n iff its AoI is
below the maximum acceptable AoI Γ = mat_ms), `{"kind": "freshest", "k": 6}` (the k cameras
with the smallest AoI), `{"kind": "wait", "wait_ms": 40}` (ω-wait: the decision of epoch t
is taken at t + ω with the frames captured since t and delivered by then; the `Decision` is
stamped t + ω, the time its render is scored against), `{"kind": "ppo", "checkpoint":
"<path>", "learn": false}` (a trained single-step PPO agent's deterministic action). A new
policy is used from the next decision on. The decision step is the experiments' own
(`aoi3d.policy.decide`): a policy selects the same frames here as on the virtual clock.

Any policy but `deadline` takes a training budget, `"budget_steps": 50` (the spec's
`mat:70@50`): each of its decisions' renders trains that many steps instead of the dispatcher's
`render_steps`. The Decision carries it (`budget_steps`) and the lag the scheduler expects
from the decision to its render on screen at that budget (`expected_lag_ms`), learned from
the Quality of its renders; the compute-aware kinds read that lag: `{"kind": "dmat",
"mat_ms": 100}` (MAT on the age at display) and `{"kind": "deadline", "mat_ms": 100,
"deadline_ms": 40}` (the largest budget on screen within the deadline).

With `"learn": true` the PPO policy keeps learning online: each decision samples the agent's
stochastic action, the metrics service's `Quality` for that decision is its reward, and every
`AOI3D_SCHEDULER_LEARN_BATCH_SIZE` rewarded decisions make one PPO update. The agent
(weights and optimizer state) is written to its online checkpoint (`save_to`, default
`<stem>.online.pt` next to the checkpoint) every `AOI3D_SCHEDULER_LEARN_CHECKPOINT_EVERY`
updates, when the policy is replaced and on shutdown. `GET /policy` shows the learning
state under `online`; Prometheus has the `aoi3d_ppo_*` series.
"""

Scheduler = Annotated[SchedulerRuntime, Depends(get_worker)]


def _none_if_nan(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


# ---------------------------------------------------------------- /policy
policy_router = APIRouter(prefix="/policy", tags=["policy"])
_READ_ONLY = {"spec", "accepted_forms", "online"}  # response fields: a GET body can be PUT back

_POLICY_EXAMPLES = {
    "mat": {"summary": "MAT with Γ = 51 ms", "value": {"kind": "mat", "mat_ms": 51}},
    "mat-budget": {"summary": "MAT with Γ = 70 ms, 50 training steps per decision",
                   "value": {"kind": "mat", "mat_ms": 70, "budget_steps": 50}},
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


def _policy_state(worker: SchedulerRuntime) -> PolicyResponse:
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


@policy_router.get("/checkpoints", summary="The PPO checkpoints a ppo policy can load.")
def get_checkpoints(request: Request) -> CheckpointList:
    roots = request.app.state.settings.common.files_roots
    return CheckpointList(checkpoints=files_in_roots(roots, "*.pt"))


# ---------------------------------------------------------------- /aoi
aoi_router = APIRouter(prefix="/aoi", tags=["aoi"])


@aoi_router.get("", summary="The current AoI vector (null = unknown).")
def get_aoi(worker: Scheduler) -> AoIResponse:
    snap = worker.aoi()
    return AoIResponse(time_ms=snap.time_ms, camera_ids=list(snap.camera_ids),
                       aoi_ms=[_none_if_nan(a) for a in snap.aoi_ms],
                       newest_ms=[_none_if_nan(u) for u in snap.newest_ms])


# ---------------------------------------------------------------- /decision
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
        policy=msg.policy, gamma_ms=msg.gamma_ms if msg.HasField("gamma_ms") else None,
        budget_steps=msg.budget_steps if msg.HasField("budget_steps") else None,
        expected_lag_ms=msg.expected_lag_ms if msg.HasField("expected_lag_ms") else None)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None) -> FastAPI:
    """The scheduler service; ``bus``/``clock`` default to Zenoh and the shared clock."""
    settings = settings or Settings()
    common = settings.common
    clock = clock or SimClock(epoch_s=common.epoch_s, time_scale=common.time_scale)
    policy = parse_policy(settings.policy).on_device(settings.device)
    policy.check_fits(common.cameras)  # fail at start-up, not at the first decision

    def build_worker(the_bus: Bus, registry, site: str) -> SchedulerRuntime:
        return SchedulerRuntime(the_bus, registry, run_id=common.run_id, site=site,
                               n_cameras=common.cameras, clock=clock, policy=policy,
                               decision_period_ms=settings.decision_period_ms,
                               inbox_size=settings.inbox_size,
                               learn=settings.learn_config(), device=settings.device,
                               stall_s=common.stall_s,
                               step_ms_prior=settings.step_ms * common.time_scale)

    app = service_app(title="aoi3d scheduler", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus, per_site=True)
    include_site_routers(app, policy_router, aoi_router, decision_router)
    return app
