"""The live pipeline switches to a PPO checkpoint, then learns online from its own rewards.

Real processes, a real Zenoh router on 127.0.0.1 and the real dispatcher and metrics services
(started by ``aoi3d up``, as in ``test_pipeline.py``, whose helpers this reuses). The
checkpoint is built so that its deterministic action is known: it selects the odd cameras,
whatever the AoI, while the pipeline starts with ``all``; so the decisions must change from
"every known camera" to "the known odd cameras". Then ``learn: true``: the metrics service's
Quality messages are the rewards, and with a batch of 2 (and renders every 0.5 s) the
scheduler must learn some episodes, update, and write its online checkpoint when the policy
is switched back.
"""

from __future__ import annotations

import math
import os
import subprocess
import time
import uuid
from pathlib import Path

import pytest

from aoi3d.policy.ppo.learner import PPOLearner
from tests.support.pipeline import (
    HTTP,
    PIPE,
    SERVICES,
    Tap,
    assert_clean_exit,
    metric,
    stop_pipeline,
    wait_for,
)
from tests.support.ppo import make_subset_checkpoint

TOKEN = "ppo-live-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}

pytestmark = [pytest.mark.integration, pytest.mark.slow]

N_CAMERAS = 18  # aoi3d up's rig
ODD = tuple(range(1, N_CAMERAS + 1, 2))


def test_live_scheduler_switches_to_ppo_and_learns_online(small_dataset: Path,
                                                          tmp_path: Path) -> None:
    ckpt = make_subset_checkpoint(tmp_path / "odd.pt", n_cameras=N_CAMERAS, subset=ODD)
    online = tmp_path / "odd.online.pt"
    run_id = f"ppo{uuid.uuid4().hex[:8]}"
    cmd = ["--dataset", str(small_dataset),
           "--run-id", run_id, "--log-dir", str(tmp_path / "logs"), "--time-scale", "0.1"]
    # control locked with a token, checkpoints in the test's folder (docs/operations.md,
    # "Reliability and security")
    env = dict(os.environ, AOI3D_SCHEDULER_POLICY="all", AOI3D_SCHEDULER_LEARN_BATCH_SIZE="2",
               AOI3D_DISPATCHER_RENDER_STEPS="20",
               AOI3D_CONTROL_TOKEN=TOKEN, AOI3D_FILES_ROOTS=str(tmp_path))
    up = PIPE.start(cmd, env=env, output=subprocess.PIPE)
    tap = None
    try:
        for name in SERVICES:
            wait_for(f"{name} /healthz",
                     lambda n=name: HTTP.get(PIPE.url(n, "/healthz")).status_code == 200)
        tap = Tap(run_id)
        sched = PIPE.url("scheduler", "/policy")
        assert HTTP.get(sched).json()["spec"] == "all"

        # under `all`, decisions use every camera with a known AoI, even ones included
        t0 = time.monotonic()
        before = wait_for("decisions using even cameras under all", lambda: [
            d for d in tap.decisions_after(t0)
            if d.policy == "all" and any(s.camera_id % 2 == 0 for s in d.selected)][:3])
        assert all(len(d.selected) == sum(map(math.isfinite, d.aoi_ms)) for d in before)

        # switch to the checkpoint: from now on, the known odd cameras and nothing else
        r = HTTP.put(sched, json={"kind": "ppo", "checkpoint": str(ckpt), "learn": False})
        assert r.status_code == 401, r.text  # no token: refused, nothing changed
        assert HTTP.get(sched).json()["spec"] == "all"
        r = HTTP.put(sched, json={"kind": "ppo", "checkpoint": str(ckpt), "learn": False},
                     headers=AUTH)
        assert r.status_code == 200, r.text
        assert r.json()["spec"] == f"ppo:{ckpt}" and r.json()["learn"] is False
        t1 = time.monotonic()
        after = wait_for("decisions of the PPO policy", lambda: [
            d for d in tap.decisions_after(t1) if d.policy == f"ppo:{ckpt}"][:5])
        for d in after:
            known_odd = [cam for cam, a in zip(d.camera_ids, d.aoi_ms, strict=True)
                         if cam % 2 == 1 and math.isfinite(a)]
            assert [s.camera_id for s in d.selected] == known_odd
            assert known_odd  # frames flow: it really selects something
        # bad checkpoints are refused, and the policy stays
        r = HTTP.put(sched, json={"kind": "ppo", "checkpoint": str(tmp_path / "none.pt")},
                     headers=AUTH)
        assert r.status_code == 422 and "no PPO checkpoint" in r.text
        assert HTTP.get(sched).json()["spec"] == f"ppo:{ckpt}"

        # learn online: the metrics service's Quality of each rendered decision is its reward
        r = HTTP.put(sched, json={"kind": "ppo", "checkpoint": str(ckpt), "learn": True},
                     headers=AUTH)
        assert r.status_code == 200, r.text
        assert r.json()["learn"] is True and r.json()["save_to"] == str(online)
        wait_for("episodes learned online",
                 lambda: metric("scheduler", "aoi3d_ppo_episodes_learned_total") >= 2,
                 timeout_s=30)
        assert metric("scheduler", "aoi3d_ppo_updates_total") >= 1
        assert metric("scheduler", "aoi3d_ppo_learning") == 1
        state = HTTP.get(sched).json()["online"]
        assert state["episodes_learned"] >= 2 and math.isfinite(state["mean_reward"])
        assert math.isfinite(metric("scheduler", "aoi3d_ppo_mean_reward"))
        assert math.isfinite(metric("scheduler", "aoi3d_ppo_policy_entropy"))

        # back to a rule: learning stops and the online checkpoint is written
        r = HTTP.put(sched, json={"kind": "all"}, headers=AUTH)
        assert r.status_code == 200, r.text
        assert metric("scheduler", "aoi3d_ppo_learning") == 0
        learned = PPOLearner.load(online)
        assert learned.episodes >= 2 and learned.updates >= 1
        assert PPOLearner.load(ckpt).episodes == 0  # the source is untouched
    finally:
        if tap is not None:
            tap.close()
        out = stop_pipeline(up)
    assert_clean_exit(up, out, run_id)
