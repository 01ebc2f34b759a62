"""PPO presets, training on a pool of environment workers, evaluation on held-out seeds.

Training (:func:`train`) runs batches of ``batch_size`` one-step episodes: the main process
resets a local :class:`~aoi3d.rl.env.FrameSelectionEnv` for each episode's seed (cheap: the
channel simulation), samples the agent's action, and hands ``(seed, action)`` to an
:class:`EnvPool` — a ``spawn`` process pool of env workers, one torch thread each, as the
experiment sweeps do — which trains and scores the radiance field. When the batch is back,
the agent makes one PPO update. Every ``checkpoint_every`` updates it writes
``checkpoint.pt`` (agent, optimizer, generator, position), ``episodes.csv``, ``updates.csv``
and ``reward.png``; at the end ``final.pt``. A run resumes from its checkpoint and, the
generator's state being in it, draws the same actions again (the episodes after the
checkpoint come back from the result cache).

Seeds: training episode i uses channel seed ``TRAIN_SEED_BASE + i``; evaluation uses
``EVAL_SEED_BASE + k`` — disjoint by construction (training is capped below
``EVAL_SEED_BASE − TRAIN_SEED_BASE`` episodes), and both disjoint from the experiment
sweeps' seeds 0, 1, 2, … (so ``aoi3d experiment compare`` scores a trained agent on channel
draws it never saw).
"""

from __future__ import annotations

import csv
import math
import multiprocessing
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aoi3d.experiment import EpisodeConfig, default_workers, get_preset, mean_ci95
from aoi3d.experiment.episode import dataset_fingerprint, set_torch_threads
from aoi3d.experiment.report import code_version, machine, write_csv, write_json
from aoi3d.policy import Policy, parse_policy
from aoi3d.policy.wait import wait_ms_of
from aoi3d.rl.agent import PPOConfig, SingleStepPPO
from aoi3d.rl.env import FrameSelectionEnv
from aoi3d.rl.policy import PPOPolicy
from aoi3d.scene import SceneDataset, open_dataset

__all__ = [
    "EVAL_SEED_BASE",
    "PPO_PRESETS",
    "TRAIN_SEED_BASE",
    "EnvPool",
    "EvalOutcome",
    "PPOPreset",
    "TrainConfig",
    "TrainProgress",
    "TrainSummary",
    "eval_seeds",
    "evaluate",
    "get_ppo_preset",
    "plot_rewards",
    "train",
    "train_seed",
]

TRAIN_SEED_BASE = 100_000
"""Channel seed of training episode 0 (episode i: ``TRAIN_SEED_BASE + i``)."""
EVAL_SEED_BASE = 1_000_000
"""First held-out seed of :func:`evaluate` (``EVAL_SEED_BASE + k``)."""
MAX_TRAIN_EPISODES = EVAL_SEED_BASE - TRAIN_SEED_BASE


def train_seed(episode: int) -> int:
    """The channel seed of training episode ``episode`` (0-based)."""
    if not 0 <= episode < MAX_TRAIN_EPISODES:
        raise ValueError(f"training episode index must be in [0, {MAX_TRAIN_EPISODES}), "
                         f"got {episode}")
    return TRAIN_SEED_BASE + episode


def eval_seeds(count: int, offset: int = 0) -> list[int]:
    """``count`` held-out seeds, the ``offset``-th first; never a training seed."""
    if count < 1 or offset < 0:
        raise ValueError(f"need count >= 1 and offset >= 0, got {count}, {offset}")
    return [EVAL_SEED_BASE + offset + k for k in range(count)]


# --- presets ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class PPOPreset:
    """A named training budget: the environment's episode config (an experiment preset's,
    with the PPO overrides), the episodes, the batch size, the agent's hyper-parameters
    (``ppo``: :class:`PPOConfig` fields but ``n_cameras``, which the dataset gives) and the
    held-out seeds of ``aoi3d ppo eval``."""

    name: str
    episode: EpisodeConfig
    episodes: int
    batch_size: int
    ppo: Mapping[str, Any]
    eval_seeds: int
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "episode": self.episode.to_dict(), "episodes": self.episodes,
                "batch_size": self.batch_size, "ppo": dict(self.ppo),
                "eval_seeds": self.eval_seeds, "note": self.note}


_PPO_HYPER = {"arch": "shared", "hidden": 64, "lr": 1e-3, "clip_eps": 0.2,
              "update_epochs": 10, "minibatch_size": 8, "ent_coef": 0.01, "vf_coef": 0.5,
              "max_grad_norm": 0.5, "init_select_p": 0.5, "aoi_scale_ms": 300.0, "seed": 0}
"""The presets' agent: the camera-shared actor learns the per-camera rule within 600
episodes where the plain MLP barely moves (docs/ppo.md, "Which network")."""

PPO_PRESETS: dict[str, PPOPreset] = {
    "quick": PPOPreset(
        name="quick",
        episode=get_preset("quick").episode.with_(steps_per_epoch=100),
        episodes=600, batch_size=16, ppo=dict(_PPO_HYPER), eval_seeds=40,
        note="the experiment quick preset's episode with 100 field steps per decision "
             "instead of 300 (≈ 3 s instead of ≈ 9 s an episode on one core; see "
             "docs/ppo.md): 600 episodes ≤ 30 min on 2 cores",
    ),
    "paper": PPOPreset(
        name="paper",
        episode=get_preset("paper").episode,
        episodes=600, batch_size=16, ppo=dict(_PPO_HYPER), eval_seeds=100,
        note="the experiment paper preset's episode (1000 steps per decision): for a GPU or "
             "many cores",
    ),
}


def get_ppo_preset(name: str) -> PPOPreset:
    """The PPO preset ``name``; ``ValueError`` listing the known ones."""
    try:
        return PPO_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown PPO preset {name!r}; known: {', '.join(PPO_PRESETS)}"
                         ) from None


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (written to ``config.json`` and the checkpoint).

    ``checkpoint_every``: updates between two checkpoints (and CSV/plot refreshes).
    """

    episode: EpisodeConfig
    ppo: PPOConfig
    episodes: int
    batch_size: int
    checkpoint_every: int = 5
    preset: str = "custom"

    def __post_init__(self) -> None:
        for name, value, low in (("episodes", self.episodes, 1),
                                 ("batch_size", self.batch_size, 1),
                                 ("checkpoint_every", self.checkpoint_every, 1)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
        if self.episodes > MAX_TRAIN_EPISODES:
            raise ValueError(f"episodes must be <= {MAX_TRAIN_EPISODES} (training seeds stay "
                             f"below the held-out ones), got {self.episodes}")

    @classmethod
    def from_preset(cls, preset: PPOPreset, n_cameras: int, **changes: Any) -> TrainConfig:
        """The preset's config for ``n_cameras`` cameras, with ``changes`` applied."""
        ppo = PPOConfig(n_cameras=n_cameras, **dict(preset.ppo))
        base = cls(episode=preset.episode, ppo=ppo, episodes=preset.episodes,
                   batch_size=preset.batch_size, preset=preset.name)
        return replace(base, **changes)

    def to_dict(self) -> dict[str, Any]:
        return {"episode": self.episode.to_dict(), "ppo": self.ppo.to_dict(),
                "episodes": self.episodes, "batch_size": self.batch_size,
                "checkpoint_every": self.checkpoint_every, "preset": self.preset}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown training config key(s) {unknown}")
        doc = dict(data)
        doc["episode"] = EpisodeConfig.from_dict(dict(doc["episode"]))
        doc["ppo"] = PPOConfig.from_dict(dict(doc["ppo"]))
        return cls(**doc)


# --- the pool of environment workers ---------------------------------------------------------
_ENV: FrameSelectionEnv | None = None


def _make_env(cfg_doc: dict[str, Any], scale: float, cache: str | None) -> FrameSelectionEnv:
    return FrameSelectionEnv(EpisodeConfig.from_dict(cfg_doc), aoi_scale_ms=scale, cache=cache)


def _init_worker(cfg_doc: dict[str, Any], scale: float, cache: str | None, threads: int
                 ) -> None:
    global _ENV
    set_torch_threads(threads)
    _ENV = _make_env(cfg_doc, scale, cache)


def _episode(env: FrameSelectionEnv, seed: int, bits: list[int]) -> dict[str, Any]:
    """Run one episode: reset to ``seed``, step with ``bits``; plain data out."""
    env.reset(seed=seed)
    _, reward, _, _, info = env.step(np.asarray(bits, dtype=np.int8))
    outcome = env.last_outcome
    assert outcome is not None
    aoi = info["aoi"]
    known = aoi[~np.isnan(aoi)]
    used = set(info["selected"])
    return {
        "seed": seed, "reward": float(reward), "psnr": info["psnr"], "ssim": info["ssim"],
        "lpips": info["lpips"], "n_selected": info["n_selected"],
        "n_known": int(known.size),
        "selected": "".join("1" if c in used else "0" for c in env.camera_ids),
        "aoi_used_ms": info["aoi_used_ms"],
        "mean_aoi_ms": float(known.mean()) if known.size else math.nan,
        "eval_ms": info["eval_ms"], "cached": outcome.cached, "wall_s": outcome.wall_s,
    }


def _work(seed: int, bits: list[int]) -> dict[str, Any]:
    if _ENV is None:
        raise RuntimeError("env worker not initialised")
    return _episode(_ENV, seed, bits)


class EnvPool:
    """Runs ``(seed, action)`` episodes of one env config: in this process (``workers=1``)
    or on a ``spawn`` process pool, one environment (dataset, LPIPS net) per worker, started
    once and reused. Use as a context manager."""

    def __init__(self, cfg: EpisodeConfig, *, aoi_scale_ms: float, cache: str | Path | None,
                 workers: int | None = None, threads: int = 1) -> None:
        self.workers = default_workers() if workers is None else workers
        if self.workers < 1 or threads < 1:
            raise ValueError(f"workers and threads must be >= 1, got {workers}, {threads}")
        self.threads = threads
        doc = cfg.to_dict()
        cache_dir = None if cache is None else str(cache)
        self._local: FrameSelectionEnv | None = None
        self._pool: ProcessPoolExecutor | None = None
        if self.workers == 1:
            self._local = _make_env(doc, aoi_scale_ms, cache_dir)
        else:
            self._pool = ProcessPoolExecutor(
                max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker, initargs=(doc, aoi_scale_ms, cache_dir, threads))

    def run(self, items: Sequence[tuple[int, np.ndarray]]) -> Iterator[tuple[int, dict[str, Any]]]:
        """Yield ``(index in items, outcome)`` as episodes finish. Identical items (same seed
        and action) are computed once; the copies come back marked ``cached``."""
        groups: dict[tuple[int, tuple[int, ...]], list[int]] = {}
        for i, (seed, action) in enumerate(items):
            bits = tuple(int(b) for b in np.asarray(action).reshape(-1))
            groups.setdefault((int(seed), bits), []).append(i)
        for key, outcome in self._unique(list(groups)):
            first, *copies = groups[key]
            yield first, outcome
            for i in copies:
                yield i, {**outcome, "cached": True, "wall_s": 0.0}

    def _unique(self, keys: list[tuple[int, tuple[int, ...]]]
                ) -> Iterator[tuple[tuple[int, tuple[int, ...]], dict[str, Any]]]:
        if self._local is not None:
            previous = torch.get_num_threads()
            set_torch_threads(self.threads)
            try:
                for key in keys:
                    yield key, _episode(self._local, key[0], list(key[1]))
            finally:
                torch.set_num_threads(previous)
            return
        assert self._pool is not None
        futures = {self._pool.submit(_work, key[0], list(key[1])): key for key in keys}
        pending: set[Future[dict[str, Any]]] = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield futures[fut], fut.result()
        finally:
            for fut in pending:
                fut.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> EnvPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- training --------------------------------------------------------------------------------
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


EPISODE_COLUMNS = ("episode", "seed", "update", "reward", "psnr", "ssim", "lpips",
                   "n_selected", "n_known", "aoi_used_ms", "mean_aoi_ms", "eval_ms",
                   "selected", "p_mean", "value", "logp", "entropy", "cached", "wall_s")


def _read_rows(path: Path, limit: int) -> list[dict[str, Any]]:
    """The first ``limit`` episode rows of an ``episodes.csv`` (numbers parsed)."""
    if not path.is_file():
        return []
    rows: list[dict[str, Any]] = []
    with path.open(newline="") as fh:
        for raw in csv.DictReader(fh):
            row: dict[str, Any] = {}
            for k, v in raw.items():
                if k in ("selected",):
                    row[k] = v
                elif k == "cached":
                    row[k] = v == "True"
                elif v == "":
                    row[k] = None
                else:
                    number = float(v)
                    row[k] = int(number) if k in ("episode", "seed", "update", "n_selected",
                                                  "n_known", "eval_ms") else number
            rows.append(row)
    return [r for r in rows if r["episode"] < limit]


def moving_average(values: Sequence[float], window: int) -> np.ndarray:
    """Trailing mean over up to ``window`` values (shorter at the start)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size == 0:
        return arr
    csum = np.cumsum(np.insert(arr, 0, 0.0))
    idx = np.arange(1, arr.size + 1)
    lo = np.maximum(0, idx - window)
    return (csum[idx] - csum[lo]) / (idx - lo)


def plot_rewards(rows: Sequence[Mapping[str, Any]], path: Path, *, title: str,
                 window: int = 50) -> Path:
    """Fig. 7: the reward of every training episode and its moving average."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    episodes = [int(r["episode"]) for r in rows]
    rewards = [float(r["reward"]) for r in rows]
    fig, ax = plt.subplots(figsize=(8, 4.2), constrained_layout=True)
    ax.plot(episodes, rewards, ".", ms=3, alpha=0.35, color="tab:blue", label="episode")
    if rewards:
        ax.plot(episodes, moving_average(rewards, window), color="tab:red", lw=2,
                label=f"moving average ({window} episodes)")
    ax.set_xlabel("episode")
    ax.set_ylabel("reward  (0.02·PSNR + 0.5·SSIM − LPIPS)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def train(
    cfg: TrainConfig,
    out: str | Path,
    *,
    dataset: SceneDataset | None = None,
    workers: int | None = None,
    threads: int = 1,
    cache: str | Path | None = None,
    resume: bool = False,
    progress: Callable[[TrainProgress], None] | None = None,
) -> TrainSummary:
    """Train a :class:`SingleStepPPO` agent on ``aoi3d/FrameSelection-v0``; see the module
    docstring for the files under ``out``. ``resume`` continues from ``out/checkpoint.pt``
    (the config must match, ``episodes`` may grow); without it an existing checkpoint is
    not overwritten (``FileExistsError``)."""
    started = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.pt"
    ds = dataset if dataset is not None else open_dataset(cfg.episode.dataset)
    env = FrameSelectionEnv(cfg.episode, ds, aoi_scale_ms=cfg.ppo.aoi_scale_ms)
    cfg = replace(cfg, episode=env.config)  # carry=fresh, dataset path as opened
    if env.n_cameras != cfg.ppo.n_cameras:
        raise ValueError(f"the PPO config has n_cameras={cfg.ppo.n_cameras} but the "
                         f"environment has {env.n_cameras} cameras")
    rows: list[dict[str, Any]] = []
    update_rows: list[dict[str, Any]] = []
    if resume:
        if not ckpt.is_file():
            raise FileNotFoundError(f"nothing to resume: no {ckpt}")
        agent, extra = SingleStepPPO.load_with_extra(ckpt)
        saved = TrainConfig.from_dict(extra["train_config"])
        if replace(saved, episodes=cfg.episodes) != cfg:
            raise ValueError(f"{ckpt} was trained with another config; resume with the same "
                             f"options (only --episodes may change), or use another --out")
        start = int(extra["next_episode"])
        if cfg.episodes < start:
            raise ValueError(f"{ckpt} has already learned from {start} episodes; ask for at "
                             f"least as many (got {cfg.episodes})")
        rows = _read_rows(out / "episodes.csv", start)
        update_rows = [dict(r) for r in extra.get("updates", [])]
        if len(rows) != start:
            raise ValueError(f"{out / 'episodes.csv'} holds {len(rows)} of the {start} "
                             "episodes the checkpoint learned from")
    else:
        if ckpt.exists():
            raise FileExistsError(f"{ckpt} exists: pass resume to continue it, or use "
                                  "another output folder")
        agent = SingleStepPPO(cfg.ppo)
        start = 0
    meta = {
        "command": "aoi3d ppo train", "train_config": cfg.to_dict(),
        "seeds": {"train": f"{TRAIN_SEED_BASE} + episode", "eval_base": EVAL_SEED_BASE},
        "dataset": dataset_fingerprint(ds), "lpips": env.lpips, "workers": workers,
        "threads_per_worker": threads, "cache": None if cache is None else str(cache),
        "resumed_at_episode": start if resume else None, "code_version": code_version(),
        "machine": machine(),
    }
    write_json(out / "config.json", meta)
    window = max(10, min(50, cfg.episodes // 12))
    title = (f"PPO training — {cfg.preset} preset, {cfg.episode.delay}, "
             f"{cfg.episode.steps_per_epoch} steps/decision, batch {cfg.batch_size}")
    computed = cached = 0
    total = cfg.episodes
    last_batch: float | None = None

    def checkpoint(next_episode: int) -> None:
        extra = {"train_config": cfg.to_dict(), "next_episode": next_episode,
                 "episode_config": cfg.episode.to_dict(), "updates": update_rows,
                 "preset": cfg.preset}
        agent.save(ckpt, extra=extra)
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
    with EnvPool(cfg.episode, aoi_scale_ms=cfg.ppo.aoi_scale_ms, cache=cache,
                 workers=workers, threads=threads) as pool:
        for first in range(start, total, cfg.batch_size):
            batch = list(range(first, min(first + cfg.batch_size, total)))
            obs, acts = [], []
            for e in batch:
                o, _ = env.reset(seed=train_seed(e))
                obs.append(o)
                acts.append(agent.act(o))
            results: dict[int, dict[str, Any]] = {}
            for i, outcome in pool.run([(train_seed(e), a.action)
                                        for e, a in zip(batch, acts, strict=True)]):
                results[i] = outcome
                computed += not outcome["cached"]
                cached += bool(outcome["cached"])
                a = acts[i]
                rows.append({
                    "episode": batch[i], "seed": outcome["seed"], "update": agent.updates,
                    "reward": outcome["reward"], "psnr": outcome["psnr"],
                    "ssim": outcome["ssim"], "lpips": outcome["lpips"],
                    "n_selected": outcome["n_selected"], "n_known": outcome["n_known"],
                    "aoi_used_ms": outcome["aoi_used_ms"],
                    "mean_aoi_ms": outcome["mean_aoi_ms"], "eval_ms": outcome["eval_ms"],
                    "selected": outcome["selected"], "p_mean": float(a.probs.mean()),
                    "value": a.value, "logp": a.logp, "entropy": a.entropy,
                    "cached": outcome["cached"], "wall_s": outcome["wall_s"],
                })
                report()
            rows.sort(key=lambda r: r["episode"])
            rewards = np.array([results[i]["reward"] for i in range(len(batch))])
            stats = agent.update(np.stack(obs), np.stack([a.action for a in acts]),
                                 np.array([a.logp for a in acts]), rewards)
            last_batch = float(rewards.mean())
            update_rows.append({"update": agent.updates, "episodes": agent.episodes,
                                "first_episode": batch[0], **stats})
            report()
            if agent.updates % cfg.checkpoint_every == 0 or batch[-1] == total - 1:
                checkpoint(batch[-1] + 1)
    agent.save(out / "final.pt", extra={"train_config": cfg.to_dict(), "next_episode": total,
                                        "episode_config": cfg.episode.to_dict(),
                                        "updates": update_rows, "preset": cfg.preset})
    wall = time.perf_counter() - started
    meta.update({"wall_s": wall, "episodes_computed": computed, "episodes_cached": cached,
                 "machine_at_end": machine()})
    write_json(out / "config.json", meta)
    rewards_all = [r["reward"] for r in rows]
    k = min(window, len(rewards_all))
    return TrainSummary(
        out=out, episodes=len(rows), updates=agent.updates, computed=computed, cached=cached,
        wall_s=wall, reward_first=float(np.mean(rewards_all[:k])),
        reward_last=float(np.mean(rewards_all[-k:])),
        files=sorted(p.name for p in out.iterdir() if p.is_file()),
    )


# --- evaluation ------------------------------------------------------------------------------
EVAL_METRICS = ("reward", "psnr", "ssim", "lpips", "n_selected", "aoi_used_ms")


@dataclass
class EvalOutcome:
    """Per-episode rows and per-policy summaries (mean and 95% half-width per metric; for
    every policy after the first, the paired difference of its reward to the first's)."""

    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    seeds: list[int]
    wall_s: float


def evaluate(
    policies: Sequence[Policy | str],
    episode: EpisodeConfig,
    seeds: Sequence[int],
    *,
    aoi_scale_ms: float = 300.0,
    dataset: SceneDataset | None = None,
    workers: int | None = None,
    threads: int = 1,
    cache: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> EvalOutcome:
    """Score ``policies`` (a ``ppo:`` policy acts deterministically) on the one-decision
    episodes of ``seeds``: each policy sees the same AoI vector and its frames train the same
    fresh model. Policies that wait (``wait:<ms>``) are refused: the environment decides at
    the epoch."""
    started = time.perf_counter()
    pols = [parse_policy(p) for p in policies]
    if not pols:
        raise ValueError("no policy to evaluate")
    for p in pols:
        if wait_ms_of(p):
            raise ValueError(f"{p.spec}: the environment decides at the epoch; waiting "
                             "policies are scored by `aoi3d experiment compare`")
    ds = dataset if dataset is not None else open_dataset(episode.dataset)
    env = FrameSelectionEnv(episode, ds, aoi_scale_ms=aoi_scale_ms)
    for p in pols:
        if isinstance(p, PPOPolicy) and p.n_cameras != env.n_cameras:
            raise ValueError(f"{p.spec} was trained for {p.n_cameras} cameras; this "
                             f"environment has {env.n_cameras}")
    items: list[tuple[int, np.ndarray]] = []
    labels: list[str] = []
    for seed in seeds:
        _, info = env.reset(seed=int(seed))
        for p in pols:
            p.reset()
            items.append((int(seed), np.asarray(p.select(info["aoi"]), dtype=np.int8)))
            labels.append(p.spec)
    rows: list[dict[str, Any]] = [{} for _ in items]
    done = 0
    with EnvPool(env.config, aoi_scale_ms=aoi_scale_ms, cache=cache, workers=workers,
                 threads=threads) as pool:
        for i, outcome in pool.run(items):
            rows[i] = {"policy": labels[i], **outcome}
            done += 1
            if progress is not None:
                progress(done, len(items))
    summary = []
    first = pols[0].spec
    by_seed = {(r["policy"], r["seed"]): r for r in rows}
    for p in pols:
        mine = [r for r in rows if r["policy"] == p.spec]
        row: dict[str, Any] = {"policy": p.spec, "n": len(mine)}
        for metric in EVAL_METRICS:
            mean, half, _ = mean_ci95(r[metric] for r in mine)
            row[metric] = mean
            row[f"{metric}_ci95"] = half
        if p.spec != first:
            diff = [by_seed[(first, r["seed"])]["reward"] - r["reward"] for r in mine]
            mean, half, _ = mean_ci95(diff)
            row["first_minus_this_reward"] = mean
            row["first_minus_this_reward_ci95"] = half
        summary.append(row)
    return EvalOutcome(rows=rows, summary=summary, seeds=[int(s) for s in seeds],
                       wall_s=time.perf_counter() - started)

