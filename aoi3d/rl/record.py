"""A training run's record: the episode rows (``episodes.csv``) and the reward plot."""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.metric import LPIPS, PSNR, REWARD, SSIM

__all__ = ["EPISODE_COLUMNS", "moving_average", "plot_rewards", "read_rows"]

EPISODE_COLUMNS = ("episode", "seed", "update", *(m.short for m in (REWARD, PSNR, SSIM, LPIPS)),
                   "n_selected", "n_known", "aoi_used_ms", "mean_aoi_ms", "eval_ms",
                   "selected", "p_mean", "value", "logp", "entropy", "cached", "wall_s")


def read_rows(path: Path, limit: int) -> list[dict[str, Any]]:
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
