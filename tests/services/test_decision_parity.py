"""The same policy on the same AoI trace selects the same frames live and on the virtual clock.

The trace is an experiment episode's links (:func:`aoi3d.experiment.episode.episode_links`:
every frame's generation and delivery slot). The experiment path is
:func:`aoi3d.experiment.plan_episode` itself; the live path is the scheduler service
(``create_app`` → :class:`services.scheduler.runtime.SchedulerRuntime`) on the in-memory bus,
fed every frame of the trace with its delivery stamp and driven by a manual clock to each
decision's time. Both must give the same decisions: the same time (t, or t + ω for
``wait:<ω>``), cameras, generation times and AoIs.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from aoi3d.clock import SimClock
from aoi3d.experiment import EpisodeConfig, plan_episode
from aoi3d.experiment.episode import EpisodeLinks, display_lag, episode_links
from aoi3d.experiment.episode.plan import render_budget
from aoi3d.policy import parse_policy
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from services.kit.membus import MemoryBus
from services.kit.settings import CommonSettings
from services.scheduler.app import create_app
from services.scheduler.settings import Settings
from tests.support.scheduler import KEYS, RUN, Harness, ManualWall, frame
from tests.support.waits import wait_for

N = 4


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=16, height=12, fps=30, duration_s=1.0, n_train=N, rotor_rpm=60.0,
                      spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", cfg)


@pytest.fixture(scope="module")
def cfg(dataset: SceneDataset) -> EpisodeConfig:
    # exp:40 links, frames every 30 ms, a decision every 30 ms up to 330 ms
    return EpisodeConfig(dataset=str(dataset.root), delay="exp:40", warmup_ms=150,
                         scored_ms=180, score_every=1, lpips=False)


@pytest.fixture
def live() -> Iterator:
    clients: list[TestClient] = []

    def start(policy: str, **settings_kw: Any) -> Harness:
        wall = ManualWall(10.0)  # the first epoch is t = 30, as in the experiment
        bus = MemoryBus()
        settings = Settings(policy=policy, decision_period_ms=30.0,
                            common=CommonSettings(run_id=RUN, cameras=N), **settings_kw)
        client = TestClient(create_app(settings, bus=bus,
                                       clock=SimClock(epoch_s=0.0, time_scale=1.0, wall=wall)))
        client.__enter__()
        clients.append(client)
        return Harness(client, bus, wall)

    yield start
    for client in clients:
        client.__exit__(None, None, None)


def publish_trace(h: Harness, links: EpisodeLinks) -> int:
    """Every frame of the links, stamped with its generation and delivery slot, published at
    once: the scheduler holds each back until the clock reaches its delivery."""
    count = 0
    for cam, gens, deliveries in zip(links.camera_ids, links.run.gen_ms, links.run.delivery_ms,
                                     strict=True):
        for seq, (gen, delivery) in enumerate(zip(gens, deliveries, strict=True)):
            h.put(KEYS.edge_frame(cam), frame(cam, float(gen), float(delivery), sequence=seq))
            count += 1
    return count


@pytest.mark.parametrize(("spec", "seed"), [("all", 3), ("mat:70", 3), ("freshest:2", 8),
                                            ("wait:45", 3), ("wait:20", 8), ("mat:70@50", 3),
                                            ("freshest:2@25", 8), ("all@100", 3)])
def test_live_scheduler_decides_as_the_experiment(spec: str, seed: int, cfg: EpisodeConfig,
                                                   dataset: SceneDataset, live) -> None:
    if parse_policy(spec).budget_steps is not None:  # a budget needs a carry that spends one
        cfg = cfg.with_(carry="fresh")
    plan = plan_episode(cfg, dataset, spec, seed)
    links = episode_links(cfg, dataset, seed, wait_ms=parse_policy(spec).wait_ms)
    assert links.camera_ids == tuple(range(1, N + 1))  # the scheduler's camera ids
    h = live(spec)
    assert publish_trace(h, links) < 1024  # fits the scheduler's inbox
    assert sum(len(d.cameras) for d in plan.decisions) > 0
    for d in plan.decisions:
        got = h.decide_at(float(d.eval_ms))  # the clock at t (+ ω): the decision comes
        assert got.policy == plan.policy
        assert got.time_ms == d.eval_ms == d.decision_ms + plan.wait_ms
        assert [r.camera_id for r in got.selected] == list(d.cameras), d
        assert [r.generation_ms for r in got.selected] == list(d.gen_ms), d
        assert [r.aoi_ms for r in got.selected] == list(d.aoi_ms), d
        known = [a for a in got.aoi_ms if a == a]
        assert len(known) == d.n_known
        # the budget travels in the decision, the same live and offline
        assert (got.budget_steps if got.HasField("budget_steps") else None) == d.budget_steps


def test_live_ppo_policy_decides_as_the_experiment(cfg: EpisodeConfig, dataset: SceneDataset,
                                                   live, tmp_path: Path) -> None:
    """A learned policy too: a fresh agent's deterministic action depends on the AoI."""
    from aoi3d.policy.ppo import PPOConfig
    from aoi3d.policy.ppo.learner import PPOLearner

    PPOLearner(PPOConfig(n_cameras=N, seed=3)).save(tmp_path / "agent.pt")
    spec = f"ppo:{tmp_path / 'agent.pt'}"
    plan = plan_episode(cfg, dataset, spec, 5)
    h = live(spec)
    publish_trace(h, episode_links(cfg, dataset, 5))
    for d in plan.decisions:
        got = h.decide_at(float(d.eval_ms))
        assert [r.camera_id for r in got.selected] == list(d.cameras), d
    assert len({d.cameras for d in plan.decisions}) > 1  # the selection follows the AoI


def test_live_plugin_policy_decides_and_moves_gamma_as_the_experiment(
        cfg: EpisodeConfig, dataset: SceneDataset, live) -> None:
    """The plug-in (issue 32) sees the same deliveries live as on the virtual clock (the
    decision step's ``deliveries``), so it takes the same Γ and selects the same frames; the
    Decision carries its Γ."""
    from aoi3d.policy import decide

    spec = "adaptive:plugin:100"  # a short memory: Γ moves within the episode
    plan = plan_episode(cfg, dataset, spec, 3)
    links = episode_links(cfg, dataset, 3)
    mine = parse_policy(spec)
    feed = links.delivery_feed()
    gammas = []
    for d in plan.decisions:
        decide(mine, d.decision_ms, links.newest_ms, deliveries=feed)
        gammas.append(mine.gamma_ms)
    assert len(set(gammas)) > 3
    h = live(spec)
    publish_trace(h, links)
    for d, gamma in zip(plan.decisions, gammas, strict=True):
        got = h.decide_at(float(d.eval_ms))
        assert got.policy == spec
        assert got.gamma_ms == pytest.approx(gamma)
        assert [r.camera_id for r in got.selected] == list(d.cameras), d
    assert h.client.get("/decision").json()["gamma_ms"] == pytest.approx(gammas[-1])


def test_live_bandit_learns_from_the_quality_topic(cfg: EpisodeConfig, dataset: SceneDataset,
                                                   live) -> None:
    """The bandit over Γ, live: each Quality on the quality topic rewards the arm that decided
    for its time; the next decision takes the next arm."""
    from services.kit.pb import aoi3d_pb2 as pb

    h = live("adaptive:bandit:8:40/130")
    publish_trace(h, episode_links(cfg, dataset, 3))
    d1 = h.decide_at(60.0)
    assert d1.gamma_ms == 40
    assert h.decide_at(90.0).gamma_ms == 40  # no reward yet
    worker = h.client.app.state.worker
    h.put(KEYS.quality, pb.Quality(decision_id=d1.decision_id, time_ms=60.0, psnr_db=21.0,
                                   ssim=0.8, reward=0.5,
                                   decision_incarnation=worker.incarnation).SerializeToString())
    wait_for(lambda: worker.policy.ucb.t == 1)
    assert worker.policy.status()["arms"][0] == {"gamma_ms": 40.0, "n": 1, "mean": 21.0}
    assert h.decide_at(120.0).gamma_ms == 130  # rewarded: the untried arm next


@pytest.mark.parametrize("spec", ["dmat:100", "dmat:100@50", "deadline:100:40"])
def test_a_compute_aware_policy_decides_live_as_the_experiment(
        spec: str, cfg: EpisodeConfig, dataset: SceneDataset, live) -> None:
    """dmat and deadline read the lag from a decision to its display: on the virtual clock the
    cost model (:func:`aoi3d.experiment.episode.display_lag`), live what the scheduler learned
    from the Quality of its renders. When the renders' lag is the cost model's (each Quality
    ready compute_ms(steps) after its decision, at the config's budget) and the scheduler's
    prior slope is the model's (one budget seen: the slope is not fitted), the live decisions
    are the experiment's: the same cameras, budget and expected lag."""
    from services.kit.pb import aoi3d_pb2 as pb

    cfg = cfg.with_(carry="fresh", steps_per_epoch=100)  # L(100) = (16 + 3.4·100)·0.1 = 35.6
    lag = display_lag(cfg)
    plan = plan_episode(cfg, dataset, spec, 3)
    mat = plan_episode(cfg, dataset, "mat:100", 3)
    assert [d.cameras for d in plan.decisions] != [d.cameras for d in mat.decisions]  # L counts
    common = CommonSettings(run_id=RUN, cameras=N)
    h = live(spec, step_ms=cfg.compute_step_ms * cfg.time_scale / common.time_scale)
    worker = h.client.app.state.worker
    steps = render_budget(cfg)
    for i in range(3):  # the renders the scheduler learns from, before its first decision
        h.put(KEYS.quality, pb.Quality(
            decision_id=i + 1, time_ms=0.0, reward=0.5, decision_incarnation=worker.incarnation,
            render_steps=steps, ready_ms=cfg.compute_ms(steps)).SerializeToString())
    wait_for(lambda: len(worker.core.lag) == 3, what="the renders observed")
    publish_trace(h, episode_links(cfg, dataset, 3))
    for d in plan.decisions:
        got = h.decide_at(float(d.eval_ms))
        assert got.policy == plan.policy
        assert [r.camera_id for r in got.selected] == list(d.cameras), d
        assert [r.aoi_ms for r in got.selected] == list(d.aoi_ms), d
        assert (got.budget_steps if got.HasField("budget_steps") else None) == d.budget_steps
        assert got.expected_lag_ms == pytest.approx(lag.lag_ms(d.budget_steps))
