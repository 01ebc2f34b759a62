"""An episode's links: the N cameras' channel simulated for its seed (:func:`episode_links`),
and the frame sizes a size-dependent channel reads (:func:`frame_sizes`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aoi3d.channel import ChannelRun, parse_channel, simulate
from aoi3d.channel.varying import check_frame_encoding, jpeg_bytes
from aoi3d.experiment.config import EpisodeConfig
from aoi3d.scene import SceneDataset

_AUX_STREAM = 0xE9
"""spawn_key of the auxiliary random stream (camera phases, scene offset); the links use the
children 0..N−1 of ``SeedSequence(seed)``, so this never collides with them."""


def train_ids(cfg: EpisodeConfig, dataset: SceneDataset) -> list[int]:
    """The episode's training cameras: the dataset's, or its first ``cfg.n_cameras``."""
    ids = list(dataset.train_ids)
    if cfg.n_cameras is None:
        return ids
    if cfg.n_cameras > len(ids):
        raise ValueError(f"n_cameras={cfg.n_cameras} but the dataset at {dataset.root} has "
                         f"only {len(ids)} training cameras")
    return ids[: cfg.n_cameras]


def _aux_rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_AUX_STREAM,)))


@dataclass(frozen=True, eq=False)
class EpisodeLinks:
    """The N links of one episode's seed: what every decision of the episode reads.

    ``camera_ids``: the training cameras, in AoI-vector order; ``phase_ms``: each camera's
    first generation slot; ``scene_offset_ms``: where in the scene's loop channel time 0
    falls; ``run``: the simulated links (:class:`aoi3d.channel.ChannelRun`), up to
    ``run.duration_ms``.
    """

    seed: int
    camera_ids: tuple[int, ...]
    phase_ms: tuple[int, ...]
    scene_offset_ms: int
    run: ChannelRun

    def newest_ms(self, t_ms: int) -> np.ndarray:
        """U(t): generation slot of each camera's newest frame delivered by slot t (NaN:
        none yet) — the ``newest_at`` of :func:`aoi3d.policy.decide.decide`."""
        if t_ms >= self.run.duration_ms:
            raise ValueError(f"the links were simulated up to {self.run.duration_ms} ms; "
                             f"a decision needs them at {t_ms} ms")
        return self.run.newest_ms(t_ms)

    def delivery_feed(self) -> Callable[[int], list[tuple[int, float, float]]]:
        """A fresh ``deliveries`` of :func:`aoi3d.policy.decide.decide`: each call returns
        the frames delivered since the previous call, up to slot s — ``(camera index,
        generation ms, delivery ms)`` in order of delivery — what an adaptive policy sees."""
        seen = np.zeros(self.run.n_cameras, dtype=np.int64)

        def deliveries(s_ms: int) -> list[tuple[int, float, float]]:
            out: list[tuple[int, float, float]] = []
            for i, (g, d) in enumerate(zip(self.run.gen_ms, self.run.delivery_ms,
                                           strict=True)):
                k = int(np.searchsorted(d, s_ms, side="right"))
                out.extend((i, float(g[j]), float(d[j])) for j in range(seen[i], k))
                seen[i] = max(seen[i], k)
            out.sort(key=lambda x: x[2])
            return out

        return deliveries

    @property
    def drop_ratio(self) -> float:
        offered = int(self.run.offered.sum())
        return float(self.run.dropped.sum() / offered) if offered else math.nan


def episode_links(cfg: EpisodeConfig, dataset: SceneDataset, seed: int, *,
                  wait_ms: int = 0) -> EpisodeLinks:
    """Simulate the links of episode ``seed`` far enough for decisions that wait
    ``wait_ms`` after the config's last epoch (channel draws from ``camera_rngs(seed, N)``;
    camera phases, then the scene offset, from the auxiliary stream of the seed)."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    seed = int(seed)
    ids = train_ids(cfg, dataset)
    n = len(ids)
    aux = _aux_rng(seed)
    phases = (aux.integers(0, cfg.period_ms, n) if cfg.camera_phase == "random"
              else np.zeros(n, dtype=np.int64))
    loop_ms = max(1, math.floor(dataset.duration_ms))
    offset = int(aux.integers(0, loop_ms)) if cfg.random_scene_offset else 0
    channel = parse_channel(cfg.delay)
    sizes = None
    if channel.size_dependent:  # a frame's transmission time depends on its encoded bytes
        table = frame_sizes(dataset, cfg.frame_encoding)
        index_ids = np.asarray(ids)

        def sizes(i: int, g: int) -> int:
            return int(table[index_ids[i], dataset.frame_index(offset + g)])
    run = simulate(channel, cfg.period_ms, n, cfg.end_ms + wait_ms + 1, seed, phase_ms=phases,
                   frame_bytes=sizes)
    return EpisodeLinks(seed=seed, camera_ids=tuple(ids),
                        phase_ms=tuple(int(p) for p in phases), scene_offset_ms=offset, run=run)


_FRAME_SIZES: dict[tuple[str, str, str], np.ndarray] = {}


def frame_sizes(dataset: SceneDataset, encoding: str = "png") -> np.ndarray:
    """(cameras, frames) int64: each frame's encoded bytes — the stored PNG (what the live
    cameras send) or JPEG at quality Q (``jpeg:Q``). Cached per dataset and encoding."""
    quality = check_frame_encoding(encoding)
    key = (str(dataset.root), dataset.config_hash, encoding)
    if key not in _FRAME_SIZES:
        out = np.zeros((len(dataset.cameras), dataset.n_frames), dtype=np.int64)
        for c in range(len(dataset.cameras)):
            for f in range(dataset.n_frames):
                if quality is None:
                    out[c, f] = len(dataset.frame_png(c, f))
                else:
                    out[c, f] = jpeg_bytes(dataset.frame(c, f), quality)
        _FRAME_SIZES[key] = out
    return _FRAME_SIZES[key]
