"""One episode on the virtual clock: channel → AoI → policy → radiance field → quality.

An episode runs in two stages, so that a sweep knows what it must compute before it trains:

1. :func:`plan_episode` (cheap, milliseconds) simulates the N links with
   :func:`aoi3d.channel.simulate` for the seed and applies the policy to the AoI vector at
   every decision epoch with :func:`aoi3d.policy.decide.decide` — the decision step the live
   scheduler takes too. The channel does not depend on what the policy selects, so the whole
   selection — which camera's frame, generated when, at which decision — is known up front:
   an :class:`EpisodePlan`. A policy that waits (``wait:<ω>``, see
   :mod:`aoi3d.policy.wait`) is asked at t + ω, and its render is scored against the truth
   at t + ω.
2. :func:`run_plan` trains a :class:`aoi3d.field.FieldTrainer` on the planned frames
   (each selected camera's newest delivered frame, generated at U_n(t)) with the configured
   budget, renders the held-out camera at each scored decision and scores it against the
   ground truth of that time (the held-out camera's frame at that time) — the only use of
   the truth — over the whole image and over the dynamic region, the pixels that changed
   since the truth at t − C and t − 2C (:func:`aoi3d.quality.dynamic_mask`).

The numbers are a function of the plan, the config and the seed alone (channel draws from
``camera_rngs(seed, N)``, camera phases and the scene offset from an auxiliary stream of the
same seed, the model's ray sampling from ``seed``): two policies that select the same frames
give the same numbers, which is what :func:`plan_key` lets a sweep exploit.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from PIL import Image

from aoi3d.channel import ChannelRun, parse_channel, simulate
from aoi3d.channel.varying import check_frame_encoding, jpeg_bytes
from aoi3d.experiment.config import EpisodeConfig
from aoi3d.field import FieldTrainer, TrainView, field_config
from aoi3d.field.carry import Reconstruction, WarmStart
from aoi3d.field.process import configure_process
from aoi3d.policy import Policy, Selection, decide, parse_policy
from aoi3d.quality import DYNAMIC_FRAMES, LpipsFn, score
from aoi3d.scene import SceneDataset, to_uint8

__all__ = [
    "ENGINE_VERSION",
    "EpisodeLinks",
    "EpisodePlan",
    "EpisodeResult",
    "EpochScore",
    "PlannedDecision",
    "dataset_fingerprint",
    "episode_links",
    "episode_result",
    "plan_episode",
    "plan_key",
    "planned_decision",
    "run_plan",
    "set_torch_threads",
    "train_ids",
]

ENGINE_VERSION = 1
"""Bump when the numbers of an unchanged plan would change (invalidates cached results)."""

_AUX_STREAM = 0xE9
"""spawn_key of the auxiliary random stream (camera phases, scene offset); the links use the
children 0..N−1 of ``SeedSequence(seed)``, so this never collides with them."""


@dataclass(frozen=True)
class PlannedDecision:
    """One decision: taken at ``decision_ms``, selecting at (and rendered for) ``eval_ms``.

    ``cameras``: the selected camera ids; ``gen_ms``: the generation slot U_n(eval_ms) of each
    one's newest delivered frame; ``aoi_ms``: their AoI at ``eval_ms``. ``n_known``: cameras
    with some delivered frame. ``train``: the model trains on this selection; ``scored``: the
    novel view is rendered and scored after it.
    """

    decision_ms: int
    eval_ms: int
    cameras: tuple[int, ...]
    gen_ms: tuple[int, ...]
    aoi_ms: tuple[float, ...]
    n_known: int
    mean_aoi_all_ms: float
    train: bool
    scored: bool

    def to_dict(self) -> dict[str, Any]:
        return {
            "decision_ms": self.decision_ms, "eval_ms": self.eval_ms,
            "cameras": list(self.cameras), "gen_ms": list(self.gen_ms),
            "aoi_ms": list(self.aoi_ms), "n_known": self.n_known,
            "mean_aoi_all_ms": self.mean_aoi_all_ms, "train": self.train, "scored": self.scored,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PlannedDecision:
        return cls(
            decision_ms=int(d["decision_ms"]), eval_ms=int(d["eval_ms"]),
            cameras=tuple(int(c) for c in d["cameras"]), gen_ms=tuple(int(g) for g in d["gen_ms"]),
            aoi_ms=tuple(float(a) for a in d["aoi_ms"]), n_known=int(d["n_known"]),
            mean_aoi_all_ms=float(d["mean_aoi_all_ms"]), train=bool(d["train"]),
            scored=bool(d["scored"]),
        )


@dataclass(frozen=True)
class EpisodePlan:
    """What an episode will train on and when it is scored (see :func:`plan_episode`)."""

    config: EpisodeConfig
    policy: str
    seed: int
    wait_ms: int
    scene_offset_ms: int
    phase_ms: tuple[int, ...]
    decisions: tuple[PlannedDecision, ...]
    drop_ratio: float

    @property
    def reported(self) -> list[PlannedDecision]:
        """Decisions of the scored span that train the model (their frames are 'used')."""
        return [d for d in self.decisions if d.train and d.decision_ms >= self.config.warmup_ms]

    def to_dict(self) -> dict[str, Any]:
        return {
            "config": self.config.to_dict(), "policy": self.policy, "seed": self.seed,
            "wait_ms": self.wait_ms, "scene_offset_ms": self.scene_offset_ms,
            "phase_ms": list(self.phase_ms), "drop_ratio": self.drop_ratio,
            "decisions": [d.to_dict() for d in self.decisions],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EpisodePlan:
        return cls(
            config=EpisodeConfig.from_dict(d["config"]), policy=str(d["policy"]),
            seed=int(d["seed"]), wait_ms=int(d["wait_ms"]),
            scene_offset_ms=int(d["scene_offset_ms"]),
            phase_ms=tuple(int(p) for p in d["phase_ms"]), drop_ratio=float(d["drop_ratio"]),
            decisions=tuple(PlannedDecision.from_dict(x) for x in d["decisions"]),
        )


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


def planned_decision(sel: Selection, camera_ids: Sequence[int], *, train: bool,
                     scored: bool) -> PlannedDecision:
    """The plan's record of one decision step's :class:`~aoi3d.policy.decide.Selection`."""
    return PlannedDecision(
        decision_ms=int(sel.decision_ms), eval_ms=int(sel.eval_ms),
        cameras=sel.cameras(camera_ids),
        gen_ms=tuple(int(g) for g in sel.gen_ms),
        aoi_ms=tuple(float(a) for a in sel.selected_aoi_ms),
        n_known=int(sel.known.sum()), mean_aoi_all_ms=sel.mean_aoi_all_ms,
        train=train, scored=scored,
    )


def plan_episode(
    cfg: EpisodeConfig, dataset: SceneDataset, policy: Policy | str, seed: int, *,
    links: EpisodeLinks | None = None,
) -> EpisodePlan:
    """Simulate the links for ``seed`` and take the policy's decision at every epoch
    (:func:`aoi3d.policy.decide.decide`; a waiting policy decides at t + ω). ``links``:
    the episode's links when the caller has them already (:func:`episode_links` of the same
    config, dataset and seed, simulated far enough for the policy's wait)."""
    pol = parse_policy(policy)
    if pol.wants_quality:
        raise ValueError(f"policy {pol.spec!r} is rewarded by the quality of its renders, so "
                         "its decisions cannot be planned before the episode is scored: run "
                         "it with aoi3d.experiment.adaptive.run_stepwise")
    pol.reset()
    wait = pol.wait_ms
    if links is None:
        links = episode_links(cfg, dataset, seed, wait_ms=wait)
    elif links.seed != seed:
        raise ValueError(f"links of seed {links.seed} given for episode seed {seed}")
    times = cfg.decision_times_ms()
    first_scored = next(i for i, t in enumerate(times) if t >= cfg.warmup_ms)
    decisions = []
    feed = links.delivery_feed()
    for i, t in enumerate(times):
        scored = i >= first_scored and (i - first_scored) % cfg.score_every == 0
        train = scored or cfg.carry in ("warm", "fork")  # they train at every decision
        sel = decide(pol, t, links.newest_ms, deliveries=feed)
        decisions.append(planned_decision(sel, links.camera_ids, train=train, scored=scored))
    return EpisodePlan(
        config=cfg, policy=pol.spec, seed=links.seed, wait_ms=wait,
        scene_offset_ms=links.scene_offset_ms, phase_ms=links.phase_ms,
        decisions=tuple(decisions), drop_ratio=links.drop_ratio,
    )


def dataset_fingerprint(dataset: SceneDataset) -> dict[str, Any]:
    """What identifies a dataset's content for the result cache."""
    return {
        "root": str(dataset.root), "layout": dataset.layout, "config_hash": dataset.config_hash,
        "fps": dataset.fps, "n_frames": dataset.n_frames, "size": [dataset.width, dataset.height],
        "cameras": len(dataset.cameras), "heldout_id": dataset.heldout_id,
        "aabb": np.asarray(dataset.aabb).tolist(),
    }


def plan_key(plan: EpisodePlan, dataset: SceneDataset, *, lpips: bool) -> str:
    """The cache key of a plan's numbers: everything they depend on, the policy's name not
    (two policies with the same selections share one result). ``lpips``: whether LPIPS will
    be computed (its weights are available and the config asks for it)."""
    cfg = plan.config
    doc = {
        "engine": ENGINE_VERSION,
        "dataset": dataset_fingerprint(dataset),
        "field": _field_dict(cfg),
        "steps_per_epoch": cfg.steps_per_epoch, "carry": cfg.carry, "device": cfg.device,
        **({"render_steps": cfg.render_steps} if cfg.carry in ("fork", "stream") else {}),
        "compute": [cfg.time_scale, cfg.compute_fixed_ms, cfg.compute_step_ms],
        "lpips": lpips, "reward": [cfg.reward.psnr, cfg.reward.ssim, cfg.reward.lpips,
                                       *([cfg.reward.psnr_dynamic, cfg.reward.ssim_dynamic]
                                         if cfg.reward.dynamic else [])],
        "seed": plan.seed, "scene_offset_ms": plan.scene_offset_ms,
        "decisions": [
            [d.eval_ms, d.cameras, d.gen_ms, d.train, d.scored] for d in plan.decisions
            if d.train or d.scored
        ],
    }
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


_OFF_WHEN = {"age_weight_tau_ms": None, "age_features": 0}
"""Field settings that change no number at these values, left out of the cache key (a key
made before they existed stays valid); ``age_scale_ms`` goes with ``age_features`` = 0."""


def _field_dict(cfg: EpisodeConfig) -> dict[str, Any]:
    fc = field_config(cfg.backend, **cfg.field)
    out = {k: v for k, v in vars(fc).items() if k != "num_threads"
           and not (k in _OFF_WHEN and v == _OFF_WHEN[k])}
    if "age_features" not in out:
        out.pop("age_scale_ms", None)
    return {"backend": cfg.backend, "type": type(fc).__name__, **out}


@dataclass(frozen=True)
class EpochScore:
    """The quality of the novel view after one scored decision; ``*_dynamic*``: over the
    dynamic region (:func:`aoi3d.quality.dynamic_mask`; None where its mask is empty)."""

    decision_ms: int
    eval_ms: int
    n_selected: int
    aoi_used_ms: float
    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float
    loss: float
    steps: int
    psnr_dynamic_db: float | None
    ssim_dynamic: float | None
    dynamic_fraction: float
    display_ms: float
    """When the render is shown: ``eval_ms`` plus its reconstruction's compute in scene time
    (:meth:`EpisodeConfig.compute_ms` of the steps it trained)."""
    psnr_display_db: float
    """The render scored against the truth at ``display_ms`` (what a viewer sees), likewise
    the other ``*_display`` scores."""
    ssim_display: float
    lpips_display: float | None
    reward_display: float
    psnr_dynamic_display_db: float | None


@dataclass(frozen=True)
class EpisodeResult:
    """An episode's numbers: per scored decision, and their means (the episode's point)."""

    key: str
    policy: str
    delay: str
    seed: int
    epochs: tuple[EpochScore, ...]
    n_selected: float
    """Mean number of cameras used per training decision of the scored span."""
    aoi_used_ms: float
    """Mean AoI (at the time it is used) of the frames used in the scored span; NaN: none."""
    mean_aoi_all_ms: float
    """Mean AoI over all cameras at those decisions (what the channel offers)."""
    drop_ratio: float
    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float
    psnr_dynamic_db: float | None
    """Mean dynamic-region PSNR over the scored decisions whose mask is not empty; None: none."""
    ssim_dynamic: float | None
    """Mean dynamic-region SSIM, likewise."""
    dynamic_fraction: float
    """Mean pixel fraction of the dynamic mask over the scored decisions."""
    train_steps: int
    wall_s: float
    compute_ms: float
    """Mean scene ms charged for a scored decision's reconstruction (display − eval time)."""
    psnr_display_db: float
    """Mean PSNR against the truth at display time (``EpochScore.display_ms``)."""
    ssim_display: float
    lpips_display: float | None
    reward_display: float
    psnr_dynamic_display_db: float | None

    def to_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k != "epochs"}
        out["epochs"] = [vars(e) for e in self.epochs]
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EpisodeResult:
        """The result :meth:`to_dict` wrote; a document lacking a field (one cached before
        the dynamic-region scores existed) raises TypeError — the sweep's cache takes it as
        a miss and recomputes it under the same key, so every result has every field."""
        data = dict(d)
        data["epochs"] = tuple(EpochScore(**e) for e in d["epochs"])
        return cls(**data)

    def relabel(self, policy: str, delay: str) -> EpisodeResult:
        """The same numbers under another policy's name (a shared, cached plan)."""
        return EpisodeResult(**{**vars(self), "policy": policy, "delay": delay})


def _mean_or_none(values: list[float | None]) -> float | None:
    """The mean of the values that are not None; None when there are none."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def _nanmean(values: list[float]) -> float:
    arr = np.asarray(values, dtype=np.float64)
    arr = arr[~np.isnan(arr)]
    return float(arr.mean()) if arr.size else math.nan


class _Frames:
    """Decoded frames of the dataset at channel times (scene time = channel time + offset).

    Keeps one :class:`TrainView` per camera — its newest — so that the trainer's per-view
    pixel cache hits while a camera's frame does not change, and memory stays bounded.
    """

    def __init__(self, dataset: SceneDataset, offset_ms: int) -> None:
        self.ds = dataset
        self.offset_ms = offset_ms
        self._views: dict[int, tuple[int, TrainView]] = {}

    def index(self, time_ms: int) -> int:
        """The scene frame shown at channel time ``time_ms``."""
        return self.ds.frame_index(time_ms + self.offset_ms)

    def view(self, camera_id: int, gen_ms: int, eval_ms: int) -> TrainView:
        """Camera ``camera_id``'s frame generated at ``gen_ms``, used for time ``eval_ms``
        (its age, ``eval_ms − gen_ms``, is what the age-aware trainers read)."""
        k = self.index(gen_ms)
        age = float(eval_ms - gen_ms)
        held = self._views.get(camera_id)
        if held is None or held[0] != k:
            held = (k, TrainView(self.ds.cameras[camera_id], self.ds.frame(camera_id, k),
                                 age_ms=age))
            self._views[camera_id] = held
        elif held[1].age_ms != age:  # the same frame, older: its pixels are shared
            held = (k, replace(held[1], age_ms=age))
            self._views[camera_id] = held
        return held[1]

    def truth(self, time_ms: float) -> np.ndarray:
        """The held-out camera's frame at ``time_ms``: the ground truth of the novel view."""
        return self.ds.frame(self.ds.heldout_id, self.index(time_ms))

    def truth_before(self, time_ms: float, period_ms: int) -> list[np.ndarray]:
        """The truth at ``time_ms`` − k·``period_ms``, k = 1..K: what the dynamic mask
        compares the truth at ``time_ms`` with."""
        return [self.truth(time_ms - k * period_ms) for k in range(1, DYNAMIC_FRAMES + 1)]


def run_plan(
    plan: EpisodePlan,
    dataset: SceneDataset,
    *,
    key: str = "",
    lpips_fn: LpipsFn | None = None,
    on_render: Callable[[PlannedDecision, np.ndarray], None] | None = None,
) -> tuple[EpisodeResult, bytes]:
    """Train, render and score the plan; returns the result and the PNG of the last render.

    ``on_render(decision, image)`` sees every scored render (float32 H×W×3 in [0, 1]).
    """
    cfg = plan.config
    started = time.perf_counter()
    trainer = FieldTrainer(field_config(cfg.backend, **cfg.field), dataset.aabb,
                           device=cfg.device, seed=plan.seed)
    rec = Reconstruction(trainer, cfg.carry, _render_budget(cfg),
                         WarmStart(cold_steps=cfg.steps_per_epoch))
    frames = _Frames(dataset, plan.scene_offset_ms)
    heldout = dataset.cameras[dataset.heldout_id]
    epochs: list[EpochScore] = []
    last_image: np.ndarray | None = None
    loss = math.nan
    for d in plan.decisions:
        if d.train:
            rec.set_views([frames.view(c, g, d.eval_ms)
                           for c, g in zip(d.cameras, d.gen_ms, strict=True)])
            loss = rec.train(cfg.steps_per_epoch)
        if not d.scored:
            continue
        rendered = rec.render_decision(heldout, time_ms=d.eval_ms)
        if rendered.render_steps:
            loss = rendered.loss
        image = rendered.image
        quality = score(image, frames.truth(d.eval_ms), cfg.reward, lpips_fn,
                        previous=frames.truth_before(d.eval_ms, cfg.period_ms))
        dyn = quality.dynamic
        # what a viewer sees: the render once its compute is done, against the truth then
        display_ms = d.eval_ms + cfg.compute_ms(rendered.render_steps)
        shown = score(image, frames.truth(display_ms), cfg.reward, lpips_fn,
                      previous=frames.truth_before(display_ms, cfg.period_ms))
        epochs.append(EpochScore(
            decision_ms=d.decision_ms, eval_ms=d.eval_ms, n_selected=len(d.cameras),
            aoi_used_ms=float(np.mean(d.aoi_ms)) if d.aoi_ms else math.nan,
            psnr_db=quality.psnr_db, ssim=quality.ssim, lpips=quality.lpips,
            reward=quality.reward, loss=float(loss), steps=rendered.steps,
            psnr_dynamic_db=dyn.psnr_db, ssim_dynamic=dyn.ssim, dynamic_fraction=dyn.fraction,
            display_ms=display_ms, psnr_display_db=shown.psnr_db, ssim_display=shown.ssim,
            lpips_display=shown.lpips, reward_display=shown.reward,
            psnr_dynamic_display_db=shown.dynamic.psnr_db if shown.dynamic else None,
        ))
        last_image = image
        if on_render is not None:
            on_render(d, image)
    result = episode_result(plan, epochs, key=key, wall_s=time.perf_counter() - started)
    return result, _png(last_image)


def episode_result(plan: EpisodePlan, epochs: Sequence[EpochScore], *, key: str = "",
                   wall_s: float = math.nan) -> EpisodeResult:
    """The episode's numbers from the scores of its scored decisions (``epochs``, in order):
    their means, and the selections of the plan's reported decisions."""
    cfg = plan.config
    used = plan.reported
    aois = [a for d in used for a in d.aoi_ms]
    lpips_values = [e.lpips for e in epochs if e.lpips is not None]
    return EpisodeResult(
        key=key, policy=plan.policy, delay=cfg.delay, seed=plan.seed, epochs=tuple(epochs),
        n_selected=float(np.mean([len(d.cameras) for d in used])) if used else 0.0,
        aoi_used_ms=float(np.mean(aois)) if aois else math.nan,
        mean_aoi_all_ms=_nanmean([d.mean_aoi_all_ms for d in used]),
        drop_ratio=plan.drop_ratio,
        psnr_db=float(np.mean([e.psnr_db for e in epochs])),
        ssim=float(np.mean([e.ssim for e in epochs])),
        lpips=float(np.mean(lpips_values)) if len(lpips_values) == len(epochs) else None,
        reward=float(np.mean([e.reward for e in epochs])),
        psnr_dynamic_db=_mean_or_none([e.psnr_dynamic_db for e in epochs]),
        ssim_dynamic=_mean_or_none([e.ssim_dynamic for e in epochs]),
        dynamic_fraction=float(np.mean([e.dynamic_fraction for e in epochs])),
        train_steps=_total_steps(plan),
        wall_s=wall_s,
        compute_ms=float(np.mean([e.display_ms - e.eval_ms for e in epochs])),
        psnr_display_db=float(np.mean([e.psnr_display_db for e in epochs])),
        ssim_display=float(np.mean([e.ssim_display for e in epochs])),
        lpips_display=(float(np.mean([e.lpips_display for e in epochs]))
                       if all(e.lpips_display is not None for e in epochs) else None),
        reward_display=float(np.mean([e.reward_display for e in epochs])),
        psnr_dynamic_display_db=_mean_or_none([e.psnr_dynamic_display_db for e in epochs]),
    )


def _render_budget(cfg: EpisodeConfig) -> int:
    """Steps spent on a scored decision's own frames: ``fresh`` trains each scored decision
    ``steps_per_epoch`` steps from scratch, ``fork`` a copy of the warm model
    ``render_steps`` steps, ``stream`` ``render_steps`` from the previous one's model (its
    cold starts ``steps_per_epoch``), ``warm`` none."""
    return {"fresh": cfg.steps_per_epoch, "fork": cfg.render_steps, "stream": cfg.render_steps,
            "warm": 0}[cfg.carry]


def _total_steps(plan: EpisodePlan) -> int:
    """Training steps an episode takes (background and per scored decision)."""
    cfg = plan.config
    background = cfg.steps_per_epoch if cfg.carry in ("warm", "fork") else 0
    per_render = _render_budget(cfg)
    total = sum((background if d.train else 0) + (per_render if d.scored else 0)
                for d in plan.decisions if d.cameras)
    if cfg.carry == "stream" and any(d.scored and d.cameras for d in plan.decisions):
        total += cfg.steps_per_epoch - cfg.render_steps  # the first, cold, start (at least)
    return total


def _png(image: np.ndarray | None) -> bytes:
    if image is None:
        return b""
    buf = io.BytesIO()
    Image.fromarray(to_uint8(image)).save(buf, "PNG")
    return buf.getvalue()


def set_torch_threads(threads: int) -> None:
    """Torch intra-op threads of this process (workers of a sweep use 1 each by default)."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    configure_process(threads)
