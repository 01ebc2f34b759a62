"""Env processes: ``(seed, action)`` one-step episodes of one env config, run in this process
or on a ``spawn`` process pool (one torch thread each, as the experiment sweeps do), each
process building its :class:`~aoi3d.rl.env.FrameSelectionEnv` (dataset, LPIPS net) once."""

from __future__ import annotations

import functools
import json
import math
import multiprocessing
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aoi3d.experiment import EpisodeConfig, default_processes
from aoi3d.experiment.episode import set_torch_threads
from aoi3d.rl.env import FrameSelectionEnv

__all__ = ["EpisodeRunner", "run_episode"]


EnvArgs = tuple[str, float, str | None, str, tuple[int, ...]]
"""What builds a process's environment: the episode config (JSON), the AoI scale, the cache,
the reward and the budgets (:class:`~aoi3d.rl.env.FrameSelectionEnv`)."""


@functools.lru_cache(maxsize=1)
def _env(cfg_json: str, scale: float, cache: str | None, reward: str = "reward",
         budgets: tuple[int, ...] = ()) -> FrameSelectionEnv:
    """This process's environment for one config: built at its first episode, then reused."""
    return FrameSelectionEnv(EpisodeConfig.from_dict(json.loads(cfg_json)), aoi_scale_ms=scale,
                             cache=cache, reward=reward, budgets=budgets)


def run_episode(env: FrameSelectionEnv, seed: int, bits: list[int]) -> dict[str, Any]:
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
        "budget": info["budget"], "lag_ms": info["lag_ms"],
        "reward_display": info["reward_display"], "psnr_display": info["psnr_display"],
    }


def _work(env_args: EnvArgs, seed: int, bits: list[int]) -> dict[str, Any]:
    """One episode in an episode process."""
    return run_episode(_env(*env_args), seed, bits)


class EpisodeRunner:
    """Runs ``(seed, action)`` episodes of one env config: in this process (``processes=1``)
    or on a ``spawn`` process pool, one environment (dataset, LPIPS net) per process, started
    once and reused. Use as a context manager."""

    def __init__(self, cfg: EpisodeConfig, *, aoi_scale_ms: float, cache: str | Path | None,
                 processes: int | None = None, threads: int = 1, reward: str = "reward",
                 budgets: tuple[int, ...] = ()) -> None:
        self.processes = default_processes() if processes is None else processes
        if self.processes < 1 or threads < 1:
            raise ValueError(f"processes and threads must be >= 1, got {processes}, {threads}")
        self.threads = threads
        self._env_args: EnvArgs = (json.dumps(cfg.to_dict(), sort_keys=True),
                                   float(aoi_scale_ms), None if cache is None else str(cache),
                                   reward, tuple(budgets))
        self._local: FrameSelectionEnv | None = None
        self._pool: ProcessPoolExecutor | None = None
        if self.processes == 1:
            self._local = FrameSelectionEnv(cfg, aoi_scale_ms=aoi_scale_ms,
                                            cache=self._env_args[2], reward=reward,
                                            budgets=tuple(budgets))
        else:
            self._pool = ProcessPoolExecutor(
                max_workers=self.processes, mp_context=multiprocessing.get_context("spawn"),
                initializer=set_torch_threads, initargs=(threads,))

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
                    yield key, run_episode(self._local, key[0], list(key[1]))
            finally:
                torch.set_num_threads(previous)
            return
        assert self._pool is not None
        futures = {self._pool.submit(_work, self._env_args, key[0], list(key[1])): key
                   for key in keys}
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

    def __enter__(self) -> EpisodeRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
