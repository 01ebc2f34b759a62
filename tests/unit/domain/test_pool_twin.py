"""The virtual clock's twin of the live pool (aoi3d.experiment.episode.pool): the live
dispatcher's code with simulated workers, each job charged its compute time."""

from __future__ import annotations

from pathlib import Path

import pytest

from aoi3d.experiment import EpisodeConfig, plan_episode
from aoi3d.experiment.episode import run_plan, run_pool_plan
from aoi3d.scene import SceneDataset
from tests.support.tiny import TINY_FIELD, tiny_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    return tiny_dataset(Path(tmp_path_factory.mktemp("twin")) / "tiny")


def config(**changes) -> EpisodeConfig:
    base = EpisodeConfig(field=dict(TINY_FIELD), warmup_ms=90, scored_ms=300, score_every=1,
                         carry="fresh", steps_per_epoch=4, lpips=False, time_scale=1.0,
                         compute_fixed_ms=10.0, compute_step_ms=0.0, pool_workers=1)
    return base.with_(**changes)


def test_a_pool_faster_than_the_decisions_renders_each_one_its_compute_time_late(
        dataset: SceneDataset) -> None:
    cfg = config()
    plan = plan_episode(cfg, dataset, "all", 0)
    res, out, image = run_pool_plan(plan, dataset)
    assert out.superseded == 0 and out.rendered == out.offered
    assert out.rendered_fraction == 1.0 and res.rendered_fraction == 1.0
    assert len(res.epochs) == out.offered_scored
    assert all(e.display_ms - e.eval_ms == pytest.approx(10.0) for e in res.epochs)
    # an empty selection (before any frame was delivered) trains nothing
    assert image is not None and res.train_steps == 4 * sum(bool(d.cameras) for d in plan.decisions)


def test_a_slow_pool_takes_the_newest_decision_and_the_rest_are_superseded(
        dataset: SceneDataset) -> None:
    cfg = config(compute_fixed_ms=40.0, compute_step_ms=5.0)  # 60 ms a job, a decision per 30
    res, out, _ = run_pool_plan(plan_episode(cfg, dataset, "all", 0), dataset)
    assert out.superseded > 0 and out.offered == out.rendered + out.superseded
    assert 0.3 < out.rendered_fraction < 0.7
    lags = [e.display_ms - e.eval_ms for e in res.epochs]
    assert min(lags) >= 60.0 and max(lags) > 60.0  # a job, plus the wait for a free worker
    # the time scale stretches the compute in scene time: a slower world, every one rendered
    slow = config(compute_fixed_ms=40.0, compute_step_ms=5.0, time_scale=0.25)
    _, out_slow, _ = run_pool_plan(plan_episode(slow, dataset, "all", 0), dataset)
    assert out_slow.superseded == 0
    # a second worker takes what the first cannot
    two = config(compute_fixed_ms=40.0, compute_step_ms=5.0, pool_workers=2)
    _, out_two, _ = run_pool_plan(plan_episode(two, dataset, "all", 0), dataset)
    assert out_two.rendered > out.rendered


def test_the_twin_runs_the_dispatchers_fresh_wait(dataset: SceneDataset) -> None:
    """With pool_fresh_fraction 0.5 a free worker never takes a decision more than half a
    period (15 ms) old while the next is due: the render is at most a job and 15 ms late.
    A 67 ms job against a 30 ms decision period: each job ends 7 ms later in the period."""
    lags = {}
    for fraction in (1.0, 0.5):
        cfg = config(compute_fixed_ms=47.0, compute_step_ms=5.0, pool_fresh_fraction=fraction)
        res, out, _ = run_pool_plan(plan_episode(cfg, dataset, "all", 0), dataset)
        assert out.offered == out.rendered + out.superseded
        lags[fraction] = [e.display_ms - e.eval_ms for e in res.epochs]
    assert max(lags[0.5]) <= 67.0 + 15.0 + 1e-6 < max(lags[1.0])
    assert sum(lags[0.5]) / len(lags[0.5]) < sum(lags[1.0]) / len(lags[1.0])


def test_the_stream_carry_chains_each_workers_jobs(dataset: SceneDataset) -> None:
    cfg = config(carry="stream", steps_per_epoch=6, render_steps=2, pool_workers=2,
                 compute_fixed_ms=40.0, compute_step_ms=1.0)
    plan = plan_episode(cfg, dataset, "all", 0)
    res, out, _ = run_pool_plan(plan, dataset)
    # each worker starts cold once (6 steps), then warm from its own previous job (2 steps)
    assert out.warm == out.rendered - 2 - sum(not d.cameras for d in plan.decisions)
    assert res.train_steps == 2 * 6 + 2 * out.warm
    again, out_again, _ = run_pool_plan(plan_episode(cfg, dataset, "all", 0), dataset)
    assert again.psnr_display_db == res.psnr_display_db and out_again == out  # deterministic


def test_a_cold_start_slower_than_the_gap_leaves_its_worker_warm_after(
        dataset: SceneDataset) -> None:
    # the cold start (6 steps) takes 700 ms, beyond the stream carry's 500-ms gap; the warm
    # ones 20: counted from its decision, the next decision would be cold again, for good
    cfg = config(carry="stream", steps_per_epoch=6, render_steps=2, pool_workers=1,
                 job_ms=((6, 700.0), (2, 20.0)), warmup_ms=900, scored_ms=300)
    plan = plan_episode(cfg, dataset, "all", 0)
    _, out, _ = run_pool_plan(plan, dataset)
    empties = sum(not d.cameras for d in plan.decisions)
    assert out.warm >= out.rendered - 1 - empties and out.rendered_scored == out.offered_scored


def test_run_plan_takes_the_twin_with_a_pool(dataset: SceneDataset) -> None:
    cfg = config()
    plan = plan_episode(cfg, dataset, "all", 0)
    direct, _, _ = run_pool_plan(plan, dataset)
    via, png = run_plan(plan, dataset)
    assert via.psnr_display_db == direct.psnr_display_db and png.startswith(b"\x89PNG")
    without = run_plan(plan_episode(cfg.with_(pool_workers=0), dataset, "all", 0), dataset)[0]
    assert without.rendered_fraction is None


@pytest.mark.parametrize(("changes", "match"), [
    ({"carry": "warm", "steps_per_epoch": 4}, "trains between jobs"),
    ({"score_every": 2}, "score_every must be 1"),
    ({"pool_workers": -1}, "pool_workers must be an int >= 0"),
    ({"pool_fresh_fraction": 1.5}, "pool_fresh_fraction must be a number in"),
])
def test_a_pool_config_it_cannot_run_is_refused(changes: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        config(**changes)
