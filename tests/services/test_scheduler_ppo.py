"""The scheduler with a PPO policy: loading checkpoints, deterministic decisions, online learning.

Like ``test_scheduler.py``, the decision thread runs on a manual clock (the test sets the sim
time; with epoch 0 and time scale 1 the wall clock in seconds is sim ms / 1000, which is
also the clock the learner's reward expiry reads). Quality messages are published on the
MemoryBus the way the metrics service would publish them.
"""

from __future__ import annotations

import hashlib
import math
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from aoi3d.clock import SimClock
from aoi3d.policy.ppo import PPOConfig
from aoi3d.policy.ppo.learner import PPOLearner
from aoi3d.rl.online import LearnConfig, online_checkpoint_path
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.scheduler.app import create_app
from services.scheduler.settings import Settings
from tests.support.metrics import value
from tests.support.ppo import make_subset_checkpoint
from tests.support.scheduler import KEYS, RUN, Harness, ManualWall, decisions, frame
from tests.support.waits import wait_for

N = 4
SUBSET = (1, 3)  # the cameras the test checkpoint selects (ids; vector positions 0 and 2)




def quality(h: Harness, decision_id: int, time_ms: float, reward: float) -> bytes:
    """A Quality as the metrics service publishes it for a decision of ``h``'s scheduler
    (only the fields the scheduler reads matter; the others are plausible)."""
    return pb.Quality(decision_id=decision_id, time_ms=time_ms, scene_time_ms=time_ms,
                      decision_incarnation=h.client.app.state.worker.incarnation,
                      psnr_db=20.0, ssim=0.5, reward=reward, reward_terms=["psnr", "ssim"],
                      truth_time_ms=time_ms).SerializeToString()


def ppo_metrics(h: Harness) -> dict[str, float | None]:
    text = h.client.get("/metrics").text
    names = ("aoi3d_ppo_learning", "aoi3d_ppo_episodes_learned_total",
             "aoi3d_ppo_updates_total", "aoi3d_ppo_mean_reward", "aoi3d_ppo_policy_entropy",
             "aoi3d_ppo_pending_rewards", "aoi3d_ppo_rewards_expired_total",
             "aoi3d_ppo_decisions_unscored_total", "aoi3d_ppo_checkpoints_total",
             "aoi3d_ppo_update_seconds_count")
    out = {name: value(text, name) for name in names}
    for reason in ("unknown", "duplicate", "late", "time_mismatch"):
        out[f"ignored_{reason}"] = value(
            text, f'aoi3d_ppo_rewards_ignored_total{{reason="{reason}"}}')
    for reason in ("malformed", "non_finite"):
        out[f"rejected_{reason}"] = value(
            text, f'aoi3d_messages_rejected_total{{reason="{reason}"}}')
    return out


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def ckpt(tmp_path: Path) -> Path:
    return make_subset_checkpoint(tmp_path / "subset.pt", n_cameras=N, subset=SUBSET)


@pytest.fixture
def make_harness() -> Iterator[Callable[..., Harness]]:
    """Like test_scheduler's, with the online-learning settings; ``stop(h)`` ends a harness
    early (the service's shutdown), the rest end after the test."""
    clients: dict[int, TestClient] = {}

    def make(policy: str = "all", *, batch: int = 2, timeout_s: float = 60.0,
             every: int = 100, start_ms: float = 10.0) -> Harness:
        wall = ManualWall(start_ms)
        bus = MemoryBus()
        cfg = Settings(policy=policy, decision_period_ms=30.0, learn_batch_size=batch,
                       learn_reward_timeout_s=timeout_s, learn_checkpoint_every=every,
                       # the tests' checkpoints live in pytest's temporary folders
                       common=CommonSettings(run_id=RUN, cameras=N,
                                             files_roots=[tempfile.gettempdir()]))
        client = TestClient(create_app(cfg, bus=bus,
                                       clock=SimClock(epoch_s=0.0, time_scale=1.0, wall=wall)))
        client.__enter__()
        h = Harness(client, bus, wall)
        clients[id(h)] = client
        return h

    def stop(h: Harness) -> None:
        clients.pop(id(h)).__exit__(None, None, None)

    make.stop = stop  # type: ignore[attr-defined]
    yield make
    for client in clients.values():
        client.__exit__(None, None, None)


def deliver_all(h: Harness, t_ms: float) -> None:
    """A frame of every camera, generated and delivered just before ``t_ms``."""
    for cam in range(1, N + 1):
        h.put(KEYS.edge_frame(cam), frame(cam, t_ms - 20.0, t_ms - 10.0))


def put_ppo(h: Harness, path: Path, **extra) -> dict:
    r = h.client.put("/policy", json={"kind": "ppo", "checkpoint": str(path), **extra})
    assert r.status_code == 200, r.text
    return r.json()


# ---------------------------------------------------------------- loading and deciding
def test_ppo_policy_decides_with_its_deterministic_action(make_harness, ckpt: Path) -> None:
    h = make_harness("all")
    deliver_all(h, 30.0)
    before = h.decide_at(30.0)
    assert [s.camera_id for s in before.selected] == [1, 2, 3, 4]

    body = put_ppo(h, ckpt)
    assert body["spec"] == f"ppo:{ckpt}" and body["learn"] is False
    assert body["checkpoint"] == str(ckpt) and "online" not in body and "save_to" not in body
    got = h.client.get("/policy").json()
    assert got == body
    assert "ppo:<checkpoint>" in got["accepted_forms"]

    deliver_all(h, 60.0)
    d = h.decide_at(60.0)
    assert d.policy == f"ppo:{ckpt}"
    assert [s.camera_id for s in d.selected] == list(SUBSET)
    assert ppo_metrics(h)["aoi3d_ppo_learning"] == 0

    # back to a rule: decisions follow it again; the GET body can be PUT back as it is
    assert h.client.put("/policy", json={"kind": "freshest", "k": 1}).status_code == 200
    assert len(h.decide_at(90.0).selected) == 1
    assert h.client.put("/policy", json=got).json()["spec"] == f"ppo:{ckpt}"
    assert [s.camera_id for s in h.decide_at(120.0).selected] == list(SUBSET)


def test_ppo_never_selects_an_unknown_camera(make_harness, ckpt: Path) -> None:
    h = make_harness(f"ppo:{ckpt}")  # as the start-up policy (spec form)
    assert h.client.get("/policy").json()["kind"] == "ppo"
    h.put(KEYS.edge_frame(1), frame(1, 0.0, 5.0))
    h.put(KEYS.edge_frame(2), frame(2, 0.0, 5.0))
    d = h.decide_at(30.0)  # camera 3 (in the subset) has no AoI yet
    assert [s.camera_id for s in d.selected] == [1]


def test_bad_ppo_checkpoints_are_rejected_with_a_clear_422(make_harness, tmp_path: Path
                                                           ) -> None:
    h = make_harness("mat:51")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"this is not a checkpoint")
    other_n = make_subset_checkpoint(tmp_path / "n5.pt", n_cameras=5, subset=(1,))
    good = make_subset_checkpoint(tmp_path / "good.pt", n_cameras=N, subset=SUBSET)
    cases = [
        ({"checkpoint": str(tmp_path / "missing.pt")}, "no PPO checkpoint at"),
        ({"checkpoint": str(garbage)}, "not a readable PPO checkpoint"),
        ({"checkpoint": str(other_n)}, "trained for 5 cameras, but there are N = 4"),
        ({}, 'ppo needs "checkpoint"'),
        ({"checkpoint": str(good), "learn": "yes"}, "learn"),
        ({"checkpoint": str(good), "gamma": 1}, "does not take key(s) ['gamma']"),
        ({"checkpoint": str(good), "save_to": str(tmp_path / "x.pt")},
         "save_to applies only to a ppo policy with learn: true"),
        ({"checkpoint": str(good), "learn": True, "save_to": str(tmp_path / "no" / "x.pt")},
         "does not exist"),
        ({"checkpoint": str(good), "learn": True, "save_to": str(tmp_path)}, "is a folder"),
    ]
    for extra, expect in cases:
        r = h.client.put("/policy", json={"kind": "ppo", **extra})
        assert r.status_code == 422, (extra, r.text)
        assert expect in str(r.json()["detail"]), (extra, r.text)
        assert h.client.get("/policy").json()["spec"] == "mat:51"  # unchanged
    assert ppo_metrics(h)["aoi3d_ppo_learning"] == 0
    assert not list(tmp_path.glob("*.online.pt"))


def test_bad_startup_ppo_policy_fails_fast(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no PPO checkpoint"):
        Settings(policy=f"ppo:{tmp_path / 'missing.pt'}")
    other_n = make_subset_checkpoint(tmp_path / "n5.pt", n_cameras=5, subset=(1,))
    with pytest.raises(ValueError, match="trained for 5 cameras"):
        create_app(Settings(policy=f"ppo:{other_n}", common=CommonSettings(cameras=N)),
                   bus=MemoryBus())


@pytest.mark.parametrize("device", ["auto", "cuda"])
def test_ppo_agent_goes_to_the_configured_device(ckpt: Path, device: str) -> None:
    """auto takes CUDA when there is one; cuda without CUDA is a clear 422, not a crash."""
    common = CommonSettings(cameras=N, files_roots=[tempfile.gettempdir()])
    app = create_app(Settings(policy="all", device=device, common=common), bus=MemoryBus())
    with TestClient(app) as client:
        r = client.put("/policy", json={"kind": "ppo", "checkpoint": str(ckpt)})
        if torch.cuda.is_available():
            assert r.status_code == 200, r.text
            assert app.state.worker.policy.device == "cuda"
        elif device == "auto":
            assert r.status_code == 200, r.text
            assert app.state.worker.policy.device == "cpu"
        else:
            assert r.status_code == 422 and "CUDA is not available" in r.text, r.text


def test_online_checkpoint_path_defaults_next_to_the_source(tmp_path: Path) -> None:
    assert online_checkpoint_path(tmp_path / "a.pt") == tmp_path / "a.online.pt"
    assert online_checkpoint_path(tmp_path / "a") == tmp_path / "a.online.pt"
    assert online_checkpoint_path(tmp_path / "a.pt", tmp_path / "a.pt") == tmp_path / "a.pt"
    with pytest.raises(ValueError, match="non-empty"):
        online_checkpoint_path(tmp_path / "a.pt", " ")
    with pytest.raises(ValueError, match="must be an int >= 1"):
        LearnConfig(batch_size=0)
    with pytest.raises(ValueError, match="reward_timeout_s"):
        LearnConfig(reward_timeout_s=math.nan)


# ---------------------------------------------------------------- online learning
def test_learning_from_quality_rewards_updates_the_agent_and_checkpoints_on_stop(
        make_harness, ckpt: Path) -> None:
    source_hash = sha256(ckpt)
    h = make_harness("all", batch=2)
    body = put_ppo(h, ckpt, learn=True)
    online = ckpt.with_name("subset.online.pt")
    assert body["learn"] is True and body["save_to"] == str(online)
    assert body["online"]["updates"] == 0 and body["online"]["batch_size"] == 2
    m = ppo_metrics(h)
    assert m["aoi3d_ppo_learning"] == 1 and m["aoi3d_ppo_episodes_learned_total"] == 0
    assert math.isnan(m["aoi3d_ppo_mean_reward"])

    ds = []
    for t in (30.0, 60.0, 90.0):
        deliver_all(h, t)
        ds.append(h.decide_at(t))
    # sampled, but the head is sure: p = 0.9997 per camera
    assert all(sorted(s.camera_id for s in d.selected) == list(SUBSET) for d in ds)
    m = ppo_metrics(h)
    assert m["aoi3d_ppo_pending_rewards"] == 3
    assert 0 < m["aoi3d_ppo_policy_entropy"] < 0.1  # 4 confident bits

    h.put(KEYS.quality, quality(h, ds[0].decision_id, ds[0].time_ms, 0.25))
    wait_for(lambda: ppo_metrics(h)["aoi3d_ppo_pending_rewards"] == 2)
    assert ppo_metrics(h)["aoi3d_ppo_updates_total"] == 0  # one short of a batch
    h.put(KEYS.quality, quality(h, ds[2].decision_id, ds[2].time_ms, 0.75))  # ds[1]: unscored
    wait_for(lambda: ppo_metrics(h)["aoi3d_ppo_updates_total"] == 1)
    m = ppo_metrics(h)
    assert m["aoi3d_ppo_episodes_learned_total"] == 2
    assert m["aoi3d_ppo_mean_reward"] == pytest.approx(0.5)
    assert m["aoi3d_ppo_decisions_unscored_total"] == 1
    assert m["aoi3d_ppo_pending_rewards"] == 0
    assert m["aoi3d_ppo_update_seconds_count"] == 1
    assert m["aoi3d_ppo_checkpoints_total"] == 0  # every 100 updates: none yet
    online_state = h.client.get("/policy").json()["online"]
    assert online_state["updates"] == 1 and online_state["episodes_learned"] == 2
    assert online_state["unscored"] == 1 and online_state["mean_reward"] == pytest.approx(0.5)
    assert set(online_state["last_update"]) >= {"policy_loss", "value_loss", "approx_kl"}
    assert not online.exists()

    learner = h.client.app.state.worker.learner
    acting = learner.acting_agent.net.state_dict()  # decisions sample from the new weights
    assert all(torch.equal(v, acting[k]) for k, v in learner.agent.net.state_dict().items())

    make_harness.stop(h)  # shutdown writes the online checkpoint
    learned = PPOLearner.load(online)
    assert learned.episodes == 2 and learned.updates == 1
    source = PPOLearner.load(ckpt)
    changed = [not torch.equal(a, b) for a, b in zip(learned.net.state_dict().values(),
                                                      source.net.state_dict().values(),
                                                      strict=True)]
    assert any(changed)  # the update moved the weights
    assert sha256(ckpt) == source_hash  # the source was never overwritten


def test_checkpoints_every_k_updates_and_when_the_policy_is_replaced(make_harness, ckpt: Path,
                                                                     tmp_path: Path) -> None:
    h = make_harness("all", batch=1, every=2)
    target = tmp_path / "live.pt"
    assert put_ppo(h, ckpt, learn=True, save_to=str(target))["save_to"] == str(target)
    for i, t in enumerate((30.0, 60.0, 90.0), start=1):
        d = h.decide_at(t)
        h.put(KEYS.quality, quality(h, d.decision_id, d.time_ms, 0.1 * i))
        wait_for(lambda i=i: ppo_metrics(h)["aoi3d_ppo_updates_total"] == i)
    m = ppo_metrics(h)
    assert m["aoi3d_ppo_checkpoints_total"] == 1  # after update 2
    assert PPOLearner.load(target).updates == 2
    # replacing the policy stops learning and saves the update made since
    assert h.client.put("/policy", json={"kind": "all"}).status_code == 200
    m = ppo_metrics(h)
    assert m["aoi3d_ppo_learning"] == 0 and m["aoi3d_ppo_checkpoints_total"] == 2
    assert math.isnan(m["aoi3d_ppo_policy_entropy"])
    assert PPOLearner.load(target).updates == 3
    assert "online" not in h.client.get("/policy").json()
    # a reward arriving now is not learned from
    d = h.decide_at(120.0)
    h.put(KEYS.quality, quality(h, d.decision_id, d.time_ms, 1.0))
    h.decide_at(150.0)
    assert ppo_metrics(h)["aoi3d_ppo_updates_total"] == 3


def test_resuming_may_overwrite_the_source_only_when_asked(make_harness, ckpt: Path) -> None:
    h = make_harness("all", batch=1)
    put_ppo(h, ckpt, learn=True, save_to=str(ckpt))
    d = h.decide_at(30.0)
    h.put(KEYS.quality, quality(h, d.decision_id, d.time_ms, 0.3))
    wait_for(lambda: ppo_metrics(h)["aoi3d_ppo_updates_total"] == 1)
    make_harness.stop(h)
    assert PPOLearner.load(ckpt).episodes == 1
    assert not ckpt.with_name("subset.online.pt").exists()


def test_odd_rewards_are_ignored_and_counted(make_harness, ckpt: Path) -> None:
    h = make_harness("all", batch=8)
    put_ppo(h, ckpt, learn=True)
    d1, d2 = h.decide_at(30.0), h.decide_at(60.0)
    h.put(KEYS.quality, quality(h, 99, 2970.0, 0.5))  # never decided
    h.put(KEYS.quality, quality(h, d2.decision_id, d2.time_ms + 30.0, 0.5))  # not d2's time
    h.put(KEYS.quality, quality(h, d1.decision_id, d1.time_ms, 0.5))  # used
    h.put(KEYS.quality, quality(h, d1.decision_id, d1.time_ms, 0.5))  # again
    h.put(KEYS.quality, b"\x08\xff\xff not a quality")
    other = pb.Quality.FromString(quality(h, d2.decision_id, d2.time_ms, 0.5))
    other.decision_incarnation += 1  # d2's id and time, but a decision of another scheduler
    h.put(KEYS.quality, other.SerializeToString())
    skipped = pb.Quality.FromString(quality(h, d2.decision_id, d2.time_ms, math.nan))
    skipped.lpips_skipped = True  # scored without LPIPS (metrics' sampling): no reward to use
    h.put(KEYS.quality, skipped.SerializeToString())
    nan_reward = pb.Quality.FromString(quality(h, d2.decision_id, d2.time_ms, 0.0))
    nan_reward.reward = math.nan
    h.put(KEYS.quality, nan_reward.SerializeToString())
    wait_for(lambda: ppo_metrics(h)["rejected_non_finite"] == 1)  # the NaN one, not skipped
    m = ppo_metrics(h)
    assert (m["ignored_unknown"], m["ignored_time_mismatch"], m["ignored_duplicate"]) == (1, 1, 1)
    assert m["rejected_malformed"] == 1
    assert m["aoi3d_ppo_pending_rewards"] == 1  # d2 still waits
    online_state = h.client.get("/policy").json()["online"]
    assert online_state["batch_filled"] == 1
    assert online_state["ignored"] == {"unknown": 1, "time_mismatch": 1, "duplicate": 1}
    assert h.decide_at(90.0).decision_id == 3  # still deciding


def test_rewards_that_never_come_expire(make_harness, ckpt: Path) -> None:
    h = make_harness("all", batch=8, timeout_s=0.1)  # 0.1 wall s = 100 sim ms here
    put_ppo(h, ckpt, learn=True)
    d1 = h.decide_at(30.0)
    h.decide_at(60.0)
    assert ppo_metrics(h)["aoi3d_ppo_rewards_expired_total"] == 0
    h.decide_at(150.0)  # d1 is 120 ms old, d2 90 ms: only d1 expires
    wait_for(lambda: ppo_metrics(h)["aoi3d_ppo_rewards_expired_total"] == 1)
    assert ppo_metrics(h)["aoi3d_ppo_pending_rewards"] == 2
    h.put(KEYS.quality, quality(h, d1.decision_id, d1.time_ms, 0.5))  # too late
    wait_for(lambda: ppo_metrics(h)["ignored_late"] == 1)
    h.wall.set_ms(1000.0)
    wait_for(lambda: ppo_metrics(h)["aoi3d_ppo_rewards_expired_total"] >= 3)
    assert h.client.get("/policy").json()["online"]["expired"] >= 3


def test_learning_decisions_are_reproducible_per_checkpoint_seed(make_harness, tmp_path: Path
                                                                 ) -> None:
    """Sampled actions come from the agent's generator (seeded by its config): two schedulers
    loading the same checkpoint take the same decisions; an even head makes them vary."""
    even = PPOLearner(PPOConfig(n_cameras=N, seed=7))
    even.save(tmp_path / "even.pt")
    runs = []
    for _ in range(2):
        h = make_harness("all")
        put_ppo(h, tmp_path / "even.pt", learn=True)
        sels = []
        for t in np.arange(1, 13) * 30.0:
            deliver_all(h, t)
            sels.append(tuple(s.camera_id for s in h.decide_at(t).selected))
        runs.append(sels)
    assert runs[0] == runs[1]
    assert len(set(runs[0])) > 3  # stochastic: p = 0.5 per camera


def test_decisions_carry_the_ppo_spec_while_learning(make_harness, ckpt: Path) -> None:
    h = make_harness("all")
    put_ppo(h, ckpt, learn=True)
    d = h.decide_at(30.0)
    assert d.policy == f"ppo:{ckpt}"
    assert [m.policy for m in decisions(h.bus)][-1] == f"ppo:{ckpt}"
    ready = h.client.get("/readyz").json()
    assert "learning online" in ready["reason"]


def test_request_paths_must_lie_in_the_files_roots(tmp_path: Path, ckpt: Path) -> None:
    """A ppo policy's checkpoint and save_to from a request resolve inside AOI3D_FILES_ROOTS
    (symlinks followed); anything else is 422 with the same message whether or not the file
    exists, and nothing is written or changed."""
    root = tmp_path / "runs"
    root.mkdir()
    inside = root / "agent.pt"
    inside.write_bytes(ckpt.read_bytes())
    (root / "escape.pt").symlink_to(ckpt)  # points outside the root
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    common = CommonSettings(cameras=N, files_roots=[str(root)])
    app = create_app(Settings(policy="all", common=common), bus=MemoryBus())
    with TestClient(app) as client:
        answers = []
        for body in ({"kind": "ppo", "checkpoint": str(ckpt)},            # exists, outside
                     {"kind": "ppo", "checkpoint": str(tmp_path / "no.pt")},  # missing, outside
                     {"kind": "ppo", "checkpoint": str(root / "escape.pt")},  # symlink out
                     {"kind": "ppo", "checkpoint": str(inside), "learn": True,
                      "save_to": str(victim)}):
            r = client.put("/policy", json=body)
            assert r.status_code == 422, r.text
            answers.append(r.json()["detail"].split(" must ")[1])
        assert len(set(answers[:3])) == 1  # the same words whether the file exists or not
        assert victim.read_text() == "keep me"
        assert client.get("/policy").json()["kind"] == "all"
        listed = client.get("/policy/checkpoints").json()["checkpoints"]
        assert [Path(p).name for p in listed] == ["agent.pt"]  # the escaping link is not listed
        r = client.put("/policy", json={"kind": "ppo", "checkpoint": str(inside)})
        assert r.status_code == 200, r.text
