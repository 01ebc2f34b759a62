"""PPO training on a pool of environment processes, resumable.

Training (:func:`train`) runs batches of ``batch_size`` one-step episodes: the main process
resets a local :class:`~aoi3d.rl.env.FrameSelectionEnv` for each episode's seed (cheap: the
channel simulation), samples the agent's action, and hands ``(seed, action)`` to an
:class:`~aoi3d.rl.runner.EpisodeRunner`, which trains and scores the radiance field. When the batch
is back, the agent makes one PPO update
(:meth:`~aoi3d.policy.ppo.learner.PPOLearner.update`, as online learning does). Every
``checkpoint_every`` updates it writes ``checkpoint.pt`` (agent, optimizer, generator,
position), ``episodes.csv``, ``updates.csv`` and ``reward.png``
(:mod:`aoi3d.rl.record`); at the end ``final.pt``. A run resumes from its checkpoint and,
the generator's state being in it, draws the same actions again (the episodes after the
checkpoint come back from the result cache). Budgets and seeds: :mod:`aoi3d.rl.presets`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.experiment.episode import dataset_fingerprint
from aoi3d.experiment.report import code_version, machine, write_csv, write_json
from aoi3d.policy.ppo.batch import Batch, Episode
from aoi3d.policy.ppo.learner import PPOLearner, Sample
from aoi3d.policy.ppo.obs import pose_features
from aoi3d.rl.env import FrameSelectionEnv
from aoi3d.rl.presets import EVAL_SEED_BASE, TRAIN_SEED_BASE, TrainConfig, train_seed
from aoi3d.rl.record import moving_average, plot_rewards, read_rows
from aoi3d.rl.runner import EpisodeRunner
from aoi3d.scene import SceneDataset, open_dataset

__all__ = ["TrainProgress", "TrainSummary", "camera_feature_values", "train"]


def camera_feature_values(features: tuple[str, ...], dataset: SceneDataset,
                          camera_ids: tuple[int, ...] | list[int]) -> tuple[float, ...]:
    """The values of the camera ``features`` for this rig's training cameras (in AoI-vector
    order), as :class:`~aoi3d.policy.ppo.config.AgentConfig` stores them (value-major)."""
    values = []
    for name in features:
        if name == "pose":
            values.append(pose_features(
                np.stack([dataset.cameras[i].c2w for i in camera_ids]),
                dataset.cameras[dataset.heldout_id].c2w))
        else:  # CAMERA_FEATURES and this function are kept in step by a test
            raise ValueError(f"no values for camera feature {name!r}")
    if not values:
        return ()
    return tuple(float(x) for x in np.concatenate(values, axis=1).T.reshape(-1))


@dataclass(frozen=True)
class TrainProgress:
    """What the progress callback sees after each finished episode."""

    done: int
    total: int
    updates: int
    last_batch_reward: float | None
    moving_reward: float | None


@dataclass
class TrainSummary:
    """What a training run produced."""

    out: Path
    episodes: int
    updates: int
    computed: int
    cached: int
    wall_s: float
    reward_first: float
    reward_last: float
    files: list[str] = field(default_factory=list)


def train(
    cfg: TrainConfig,
    out: str | Path,
    *,
    dataset: SceneDataset | None = None,
    processes: int | None = None,
    threads: int = 1,
    cache: str | Path | None = None,
    resume: bool = False,
    progress: Callable[[TrainProgress], None] | None = None,
) -> TrainSummary:
    """Train a :class:`PPOLearner` agent on ``aoi3d/FrameSelection-v0``; see the module
    docstring for the files under ``out``. ``resume`` continues from ``out/checkpoint.pt``
    (the config must match, ``episodes`` may grow); without it an existing checkpoint is
    not overwritten (``FileExistsError``)."""
    started = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.pt"
    ds = dataset if dataset is not None else open_dataset(cfg.episode.dataset)
    env = FrameSelectionEnv(cfg.episode, ds, observe_lag=cfg.ppo.lag, **_env_options(cfg))
    cfg = replace(cfg, episode=env.config)  # carry=fresh, dataset path as opened
    _check_rig(cfg, env, ds)
    agent, start, rows, update_rows = _resume_or_start(cfg, out, ckpt, resume)
    meta = _meta(cfg, ds, env, processes=processes, threads=threads, cache=cache,
                 resumed_at=start if resume else None)
    write_json(out / "config.json", meta)
    window = max(10, min(50, cfg.episodes // 12))
    title = (f"PPO training — {cfg.preset} preset, {cfg.episode.delay}, "
             f"{cfg.episode.steps_per_epoch} steps/decision, batch {cfg.batch_size}")
    computed = cached = 0
    total = cfg.episodes
    last_batch: float | None = None

    def checkpoint(next_episode: int) -> None:
        agent.save(ckpt, extra=_extra(cfg, next_episode, update_rows))
        write_csv(out / "episodes.csv", rows)
        write_csv(out / "updates.csv", update_rows)
        if rows:
            plot_rewards(rows, out / "reward.png", title=title, window=window)

    def report() -> None:
        if progress is None:
            return
        moving = (float(moving_average([r["reward"] for r in rows], window)[-1])
                  if rows else None)
        progress(TrainProgress(len(rows), total, agent.updates, last_batch, moving))

    report()
    with EpisodeRunner(cfg.episode, cache=cache, processes=processes, threads=threads,
                 **_env_options(cfg)) as pool:
        for first in range(start, total, cfg.batch_size):
            batch = list(range(first, min(first + cfg.batch_size, total)))
            obs, acts = _observe_and_sample(env, agent, batch, cfg.seed_offset)
            results: dict[int, dict[str, Any]] = {}
            for i, outcome in pool.run([(train_seed(e, cfg.seed_offset), a.action)
                                        for e, a in zip(batch, acts, strict=True)]):
                results[i] = outcome
                computed += not outcome["cached"]
                cached += bool(outcome["cached"])
                rows.append(_episode_row(batch[i], outcome, acts[i], agent.updates))
                report()
            rows.sort(key=lambda r: r["episode"])
            episodes = [Episode(obs=o, action=a.action, logp=a.logp,
                                reward=results[i]["reward"])
                        for i, (o, a) in enumerate(zip(obs, acts, strict=True))]
            stats = agent.update(Batch.of(episodes))
            last_batch = float(np.mean([e.reward for e in episodes]))
            update_rows.append({"update": agent.updates, "episodes": agent.episodes,
                                "first_episode": batch[0], **stats})
            report()
            if agent.updates % cfg.checkpoint_every == 0 or batch[-1] == total - 1:
                checkpoint(batch[-1] + 1)
    agent.save(out / "final.pt", extra=_extra(cfg, total, update_rows))
    wall = time.perf_counter() - started
    meta.update({"wall_s": wall, "episodes_computed": computed, "episodes_cached": cached,
                 "machine_at_end": machine()})
    write_json(out / "config.json", meta)
    return _summary(out, rows, agent.updates, computed=computed, cached=cached, wall_s=wall,
                    window=window)


def _env_options(cfg: TrainConfig) -> dict[str, Any]:
    """What the training env and its processes are built with besides the episode config."""
    return {"aoi_scale_ms": cfg.ppo.aoi_scale_ms, "reward": cfg.reward, "budgets": cfg.budgets}


def _check_rig(cfg: TrainConfig, env: FrameSelectionEnv, ds: SceneDataset) -> None:
    """The agent's config fits the environment's rig: its camera count and features."""
    if env.n_cameras != cfg.ppo.n_cameras:
        raise ValueError(f"the PPO config has n_cameras={cfg.ppo.n_cameras} but the "
                         f"environment has {env.n_cameras} cameras")
    if cfg.ppo.camera_features != camera_feature_values(cfg.ppo.features, ds, env.camera_ids):
        raise ValueError(f"the agent's camera_features are not those of this rig's cameras "
                         f"for features {list(cfg.ppo.features)} (see camera_feature_values)")


def _resume_or_start(cfg: TrainConfig, out: Path, ckpt: Path, resume: bool
                     ) -> tuple[PPOLearner, int, list[dict[str, Any]], list[dict[str, Any]]]:
    """The agent, the first episode to run, and the episode and update rows so far: from
    ``ckpt`` (checked against ``cfg`` and ``out/episodes.csv``) or a new agent."""
    if not resume:
        if ckpt.exists():
            raise FileExistsError(f"{ckpt} exists: pass resume to continue it, or use "
                                  "another output folder")
        return PPOLearner(cfg.ppo), 0, [], []
    if not ckpt.is_file():
        raise FileNotFoundError(f"nothing to resume: no {ckpt}")
    agent, extra = PPOLearner.load_with_extra(ckpt)
    saved = TrainConfig.from_dict(extra["train_config"])
    if replace(saved, episodes=cfg.episodes) != cfg:
        raise ValueError(f"{ckpt} was trained with another config; resume with the same "
                         f"options (only --episodes may change), or use another --out")
    start = int(extra["next_episode"])
    if cfg.episodes < start:
        raise ValueError(f"{ckpt} has already learned from {start} episodes; ask for at "
                         f"least as many (got {cfg.episodes})")
    rows = read_rows(out / "episodes.csv", start)
    update_rows = [dict(r) for r in extra.get("updates", [])]
    if len(rows) != start:
        raise ValueError(f"{out / 'episodes.csv'} holds {len(rows)} of the {start} "
                         "episodes the checkpoint learned from")
    return agent, start, rows, update_rows


def _meta(cfg: TrainConfig, ds: SceneDataset, env: FrameSelectionEnv, *, processes: int | None,
          threads: int, cache: str | Path | None, resumed_at: int | None) -> dict[str, Any]:
    """``config.json``: the run's config, seeds, dataset, code and machine."""
    return {
        "command": "aoi3d ppo train", "train_config": cfg.to_dict(),
        "seeds": {"train": f"{TRAIN_SEED_BASE + cfg.seed_offset} + episode",
                  "eval_base": EVAL_SEED_BASE},
        "dataset": dataset_fingerprint(ds), "lpips": env.lpips, "processes": processes,
        "threads_per_process": threads, "cache": None if cache is None else str(cache),
        "resumed_at_episode": resumed_at, "code_version": code_version(),
        "machine": machine(),
    }


def _summary(out: Path, rows: list[dict[str, Any]], updates: int, *, computed: int,
             cached: int, wall_s: float, window: int) -> TrainSummary:
    rewards_all = [r["reward"] for r in rows]
    k = min(window, len(rewards_all))
    return TrainSummary(
        out=out, episodes=len(rows), updates=updates, computed=computed, cached=cached,
        wall_s=wall_s, reward_first=float(np.mean(rewards_all[:k])),
        reward_last=float(np.mean(rewards_all[-k:])),
        files=sorted(p.name for p in out.iterdir() if p.is_file()),
    )


def _extra(cfg: TrainConfig, next_episode: int, update_rows: list[dict[str, Any]]
           ) -> dict[str, Any]:
    """What a checkpoint (and ``final.pt``) stores beside the agent."""
    return {"train_config": cfg.to_dict(), "next_episode": next_episode,
            "episode_config": cfg.episode.to_dict(), "updates": update_rows,
            "preset": cfg.preset}


def _observe_and_sample(env: FrameSelectionEnv, agent: PPOLearner, batch: list[int],
                        seed_offset: int) -> tuple[list[np.ndarray], list[Sample]]:
    """Each episode of ``batch``: its observation and the agent's sampled action."""
    obs, acts = [], []
    for e in batch:
        # the agent observes the AoI vector its own way (its rig's features, the lag)
        _, info = env.reset(seed=train_seed(e, seed_offset))
        o = agent.observe(info["aoi"], info["lag_ms"])
        obs.append(o)
        acts.append(agent.sample(o))
    return obs, acts


def _episode_row(episode: int, outcome: dict[str, Any], a: Sample, update: int
                 ) -> dict[str, Any]:
    """The ``episodes.csv`` row of one episode's outcome and the action that made it."""
    return {
        "episode": episode, "seed": outcome["seed"], "update": update,
        "reward": outcome["reward"], "psnr": outcome["psnr"],
        "ssim": outcome["ssim"], "lpips": outcome["lpips"],
        "n_selected": outcome["n_selected"], "n_known": outcome["n_known"],
        "aoi_used_ms": outcome["aoi_used_ms"],
        "mean_aoi_ms": outcome["mean_aoi_ms"], "eval_ms": outcome["eval_ms"],
        "selected": outcome["selected"], "p_mean": float(a.probs.mean()),
        "value": a.value, "logp": a.logp, "entropy": a.entropy,
        "cached": outcome["cached"], "wall_s": outcome["wall_s"],
        "budget": outcome["budget"], "lag_ms": outcome["lag_ms"],
        "reward_display": outcome["reward_display"], "psnr_display": outcome["psnr_display"],
    }
