"""What an experiment writes next to its numbers: the code version, the machine, the config,
and the CSV/JSON files themselves (strict JSON: NaN is written as null); and one run of an
``aoi3d experiment`` command (:class:`ExperimentRun`): its settings, the ``meta`` of its
results document and the files every command writes."""

from __future__ import annotations

import csv
import json
import math
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

import aoi3d
from aoi3d.experiment.sweep import lpips_available

if TYPE_CHECKING:
    from aoi3d.experiment.config import EpisodeConfig, Preset
    from aoi3d.experiment.episode import EpisodeResult
    from aoi3d.experiment.sweep import ResultCache, SweepOutcome
    from aoi3d.scene import SceneDataset

__all__ = ["ExperimentRun", "code_version", "episode_rows", "machine", "to_jsonable",
           "write_csv", "write_json"]


def code_version() -> str:
    """``git describe --always --dirty --tags`` of the checkout aoi3d runs from, else the
    package version."""
    root = Path(aoi3d.__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--tags"], cwd=root, capture_output=True,
            text=True, timeout=10, check=True,
        )
        described = out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        described = ""
    version = getattr(aoi3d, "__version__", "unknown")
    return f"{described} (aoi3d {version})" if described else f"aoi3d {version}"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine() -> dict[str, Any]:
    """The machine the numbers were computed on (the local one; Ray nodes are not listed)."""
    info: dict[str, Any] = {
        "hostname": platform.node(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if hasattr(os, "getloadavg"):
        info["loadavg"] = [round(x, 2) for x in os.getloadavg()]
    return info


def to_jsonable(value: Any) -> Any:
    """``value`` with NaN/inf floats as None, tuples as lists, numpy scalars as Python."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, str | bytes):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: Path, doc: Any) -> Path:
    """Strict JSON, indented."""
    path.write_text(json.dumps(to_jsonable(doc), indent=1, allow_nan=False) + "\n")
    return path


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """One line per row; columns in first-seen order; NaN/None as empty cells."""
    columns: list[str] = []
    for row in rows:
        columns.extend(k for k in row if k not in columns)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if v is None else v) for k, v in to_jsonable(row).items()})
    return path


def episode_rows(results: Sequence[EpisodeResult]) -> list[dict[str, Any]]:
    """``episodes.csv``: one row per episode, without its per-decision scores."""
    return [{k: v for k, v in r.to_dict().items() if k != "epochs"} for r in results]


@dataclass
class ExperimentRun:
    """One run of an ``aoi3d experiment`` command: what it runs (preset, episode config,
    dataset, seeds), where (processes, threads, Ray), and where it writes (``out``, the episode
    cache)."""

    command: str
    preset: Preset
    cfg: EpisodeConfig
    dataset: SceneDataset
    out: Path
    cache: ResultCache
    seeds: int
    processes: int
    threads: int
    ray_address: str | None
    started: float
    seed_offset: int = 0

    @property
    def seed_list(self) -> list[int]:
        """The seeds of every point: ``seed_offset … seed_offset + seeds − 1``."""
        return list(range(self.seed_offset, self.seed_offset + self.seeds))

    @property
    def seed_span(self) -> str:
        """The seeds for a title: ``first–last`` (one number for one seed)."""
        first, last = self.seed_list[0], self.seed_list[-1]
        return f"{first}" if first == last else f"{first}–{last}"

    def meta(self, outcomes: Sequence[SweepOutcome], args: dict[str, Any]) -> dict[str, Any]:
        """``meta`` of results.json: the command, its arguments, the preset and config, the
        seeds, where it ran, the code version, the machine and the cost."""
        episode_s = [r.wall_s for o in outcomes for r in o.results]
        return {
            "command": f"aoi3d experiment {self.command}",
            "args": args,
            "preset": self.preset.to_dict(),
            "episode_config": self.cfg.to_dict(),
            "lpips": lpips_available(self.cfg),
            "seeds": self.seeds,
            "seed_offset": self.seed_offset,
            "seed_list": self.seed_list,
            "processes": self.processes if self.ray_address is None else None,
            "threads_per_process": self.threads,
            "ray_address": self.ray_address,
            "code_version": code_version(),
            "machine": machine(),
            "wall_s": time.time() - self.started,
            "episodes_computed": sum(o.computed for o in outcomes),
            "episodes_cached": sum(o.cached for o in outcomes),
            "episode_wall_s_mean": float(np.mean(episode_s)) if episode_s else None,
        }

    def write(self, outcomes: Sequence[SweepOutcome], args: dict[str, Any],
              episodes: Sequence[EpisodeResult], csvs: dict[str, Sequence[dict[str, Any]]],
              **doc: Any) -> None:
        """What every command writes to ``out``: the CSVs in ``csvs`` (file name → rows),
        ``episodes.csv`` (one row per episode) and ``results.json`` (``meta`` — the command,
        its arguments, the config, the code version and the machine —, then ``doc``, then
        the episodes with their per-decision scores)."""
        meta = self.meta(outcomes, args)
        for name, rows in csvs.items():
            write_csv(self.out / name, rows)
        write_csv(self.out / "episodes.csv", episode_rows(episodes))
        write_json(self.out / "results.json", {"meta": meta, **doc,
                                               "episodes": [r.to_dict() for r in episodes]})
