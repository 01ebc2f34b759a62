"""The configuration of one episode on the virtual clock, and the named presets.

An episode is a stretch of simulated time (1 ms slots) in which N cameras generate a frame
every ``period_ms`` (C) and offer it to their D/G/1/0 links, and a decision is taken every
``decision_period_ms`` at t = k·period + ``decision_offset_ms`` (the live scheduler's
schedule). The first ``warmup_ms`` bring the links (and, with ``carry="warm"``, the model) to
a steady state; decisions in the next ``scored_ms`` are the ones the episode reports, every
``score_every``-th of them is scored (render of the held-out view against the truth).

Model carry-over (``carry``):

- ``fresh`` (the presets' choice) — a new model at every scored decision, trained
  ``steps_per_epoch`` steps on that decision's selection only: the paper's per-time
  reconstruction, and the live trainer's default. Each scored render reflects exactly the
  frames the policy chose, scored decisions are independent samples, and unscored decisions
  cost nothing.
- ``warm`` — one model for the whole episode, trained ``steps_per_epoch`` steps on the
  selection of every decision (the live trainer's former design: the training set is
  swapped, the model kept). Measured on the turbine scene (18 cameras, E[Y] = 60 ms,
  30 steps per 30 ms decision): the model was still improving through the scored span
  after a 0.9 s warm-up, and its update rate (≈ a quarter of the pixels touched per
  decision) makes the model lag its frames by several decisions, so the freshness of the
  frames is blurred by the model's own lag; it needs long warm-ups to be comparable.
- ``fork`` — the warm model, trained ``steps_per_epoch`` steps at every decision, is the start
  of each scored decision's reconstruction: a copy of it trains ``render_steps`` more steps on
  exactly that decision's frames and renders the held-out view. Measured on the rotor scene
  it loses the tradeoff, as ``warm`` does; the live trainer renders with ``fresh``
  (docs/experiments.md, "Which carry keeps the tradeoff live"). :mod:`aoi3d.field.carry` is
  the one implementation of these modes, used here and by the trainer service.
- ``stream`` — the streaming warm start (issue 33): each scored decision starts from the
  previous scored decision's model and trains ``render_steps`` steps on its own frames, a
  share of each batch drawn from the pixels that changed since (:class:`aoi3d.field.carry.
  WarmStart`); the first scored decision, or one whose previous model is more than
  ``WarmStart.max_gap_ms`` (500 ms) older, starts cold with ``steps_per_epoch`` steps (the
  closer the scored decisions, the better the warm start: ``score_every=1`` at a 30 ms
  period is what the live pool does). Like
  ``fresh``, unscored decisions cost nothing.

The pool (``pool_workers`` ≥ 1): the twin of the live pipeline's pool of reconstruction
workers (:mod:`aoi3d.experiment.episode.pool`). Every decision is offered, as live, to the
live dispatcher's code (:class:`aoi3d.pool.Dispatcher`) at its time; ``pool_workers`` simulated
workers, each with its own model (the ``stream`` carry's warm chain runs through the jobs of
one worker), take the newest, and a job occupies its worker for :meth:`EpisodeConfig.compute_ms`
of its steps and frames (``job_ms``, wall ms measured by step count and frames, else
``compute_fixed_ms`` + ``compute_step_ms`` · steps; times ``time_scale``): what the live
workers' own timings say (``Render.compute_s``, the trainer's ``GET /status`` ``job_s``).
``pool_fresh_fraction`` is the dispatcher's ``fresh_fraction`` (the live trainer's
``AOI3D_DISPATCHER_FRESH_FRACTION``: a free worker waits for the next decision rather than take a
pending one older than that fraction of the period). The decisions the workers cannot take
are superseded; the ones rendered in the scored span are scored, at decision and at display
time (the job's end).
``score_every`` is then 1: the pool, not a schedule, chooses which decisions are rendered.
0 (the default): no pool, every ``score_every``-th decision rendered, charged its compute
but never queued (the engine of the experiments' figures).

Compute is fixed per decision, whatever the policy selects; an empty selection trains
nothing (as in the live trainer) and the render shows the model as it is (fresh: untrained).

Cameras capture in sync (``camera_phase="sync"``, as the live rig) and decisions fall on
capture slots, so the AoI at a decision is a multiple of C: every Γ in (kC, (k+1)C] selects
the same frames, and the sweep computes such points once (see
:func:`aoi3d.experiment.episode.plan_key`). ``camera_phase="random"`` models unsynchronised
cameras (continuous AoI).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from dataclasses import field as dc_field
from typing import Any

from aoi3d.channel.varying import check_frame_encoding, parse_channel
from aoi3d.field.carry import CARRY_MODES, FINETUNE_MODES, CarryMode, check_carry
from aoi3d.quality import RewardWeights
from aoi3d.scene.framings import FRAMING_DATASETS, FRAMING_SCENES

__all__ = [
    "CAMERA_PHASES",
    "CARRY_MODES",
    "EXPERIMENT_DATASET",
    "EXPERIMENT_SCENE",
    "POOL_CARRIES",
    "PRESETS",
    "EpisodeConfig",
    "Preset",
    "get_preset",
]

EXPERIMENT_SCENE = FRAMING_SCENES["rotor"]  # SceneConfig(framing="rotor", rotor_rpm=6.0)
"""The scene of the experiments: the turbine's rotor in close-up from a 60° forward-facing arc
(DyNeRF-like), turning at 6 rpm (a utility-scale rotor's speed; 3 blade passes per 10-s loop).

Why not the default scene (``framing="site"``, 18 rpm): there the blades are a few per cent
of the pixels, so a frame's age costs little (18 views: 30.0, 28.5, 27.0, 26.4 dB at 0, 1, 2,
5 frames old) while missing views cost the ground and the tower; PSNR rose with Γ to a plateau
(quick preset, E[Y] = 60 ms: 26.8 dB at Γ = 100 ms, 27.3 dB at 160 ms and with ``all``). In
the close-up the blades are a large share of the pixels, age costs more frame by frame (18
views: 31.4, 27.8, 24.7, 23.1, 21.6 dB at 0, 1, 2, 3, 5 frames old), and from the narrower
arc five views one frame old render the central novel view as well as eighteen (27.6 dB
against 27.8); at 18 rpm one frame of age already cost 7 dB, so even the freshest frames were
too stale to trade against. Measured with ``bench/staleness.py``; See docs/experiments.md."""
COMPUTE_FIXED_MS = 16.0
"""Wall ms of a reconstruction besides its steps (views, render of the held-out view), one
CPU core, the grid backend at 96×72: the cost model's intercept (docs/performance.md,
"Streaming reconstruction")."""
COMPUTE_STEP_MS = 3.4
"""Wall ms per training step (1024 rays, the grid, one core): the cost model's slope."""
EXPERIMENT_DATASET = FRAMING_DATASETS["rotor"]  # "data/turbine-rotor"
"""Where the experiments' scene is generated (when missing or of another config)."""
CAMERA_PHASES = ("sync", "random")
POOL_CARRIES = ("fresh", "stream")
"""The carries the pool's twin runs (``pool_workers`` ≥ 1): a job's model is made by the job
alone (``fresh``) or continues its worker's previous job's (``stream``)."""


def _int_at_least(name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")


@dataclass(frozen=True)
class EpisodeConfig:
    """Everything that determines an episode's numbers, except the policy and the seed.

    ``dataset``: a folder :func:`aoi3d.scene.open_dataset` reads (the commands generate
    :data:`EXPERIMENT_SCENE` at :data:`EXPERIMENT_DATASET` when it is missing).
    ``n_cameras``: the first N training cameras of the dataset (None: all).
    ``camera_phase``: ``sync`` — every camera generates at t = k·C, as the live rig does —
    or ``random`` — camera n at k·C + φ_n with φ_n uniform in [0, C) drawn from the seed.
    ``random_scene_offset``: the episode's slot 0 shows the scene at a time drawn from the seed
    (uniform over the loop), so that seeds see different phases of the motion; else at scene
    time 0. ``field``: overrides of the backend's default config
    (``aoi3d.field.field_config(backend, **field)``).
    """

    dataset: str = EXPERIMENT_DATASET
    backend: str = "grid"
    field: dict[str, Any] = dc_field(default_factory=dict)
    delay: str = "exp:60"
    frame_encoding: str = "png"
    period_ms: int = 30
    n_cameras: int | None = None
    camera_phase: str = "sync"
    decision_period_ms: int = 30
    decision_offset_ms: int = 0
    warmup_ms: int = 1500
    scored_ms: int = 1500
    score_every: int = 5
    steps_per_epoch: int = 10
    carry: CarryMode = "warm"
    render_steps: int = 0
    random_scene_offset: bool = True
    lpips: bool = True
    reward: RewardWeights = dc_field(default_factory=RewardWeights)
    device: str = "cpu"
    time_scale: float = 0.1
    compute_fixed_ms: float = COMPUTE_FIXED_MS
    compute_step_ms: float = COMPUTE_STEP_MS
    pool_workers: int = 0
    pool_fresh_fraction: float = 1.0
    job_ms: tuple[tuple[int, int, float], ...] = ()

    def __post_init__(self) -> None:
        parse_channel(self.delay)  # raises DelaySpecError listing the accepted forms
        check_frame_encoding(self.frame_encoding)
        if isinstance(self.reward, dict):
            object.__setattr__(self, "reward", RewardWeights(**self.reward))
        if not isinstance(self.field, dict):
            object.__setattr__(self, "field", dict(self.field))
        for name in ("period_ms", "decision_period_ms", "scored_ms", "score_every",
                     "steps_per_epoch"):
            _int_at_least(name, getattr(self, name), 1)
        for name in ("decision_offset_ms", "warmup_ms"):
            _int_at_least(name, getattr(self, name), 0)
        if self.n_cameras is not None:
            _int_at_least("n_cameras", self.n_cameras, 1)
        check_carry(self.carry, self.steps_per_epoch if self.carry == "fresh"
                    else self.render_steps)
        if self.carry not in FINETUNE_MODES and self.render_steps:
            raise ValueError(f"render_steps applies to carry 'fork' and 'stream' only (carry "
                             f"{self.carry!r} got render_steps={self.render_steps})")
        if self.camera_phase not in CAMERA_PHASES:
            raise ValueError(
                f"camera_phase must be one of {CAMERA_PHASES}, got {self.camera_phase!r}")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {self.device!r}")
        for name in ("time_scale", "compute_fixed_ms", "compute_step_ms"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                    math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if not self.time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {self.time_scale}")
        _int_at_least("pool_workers", self.pool_workers, 0)
        f = self.pool_fresh_fraction
        if isinstance(f, bool) or not isinstance(f, int | float) or not 0 <= f <= 1:
            raise ValueError(f"pool_fresh_fraction must be a number in [0, 1] (the live "
                             f"trainer's AOI3D_DISPATCHER_FRESH_FRACTION), got {f!r}")
        try:  # (steps, views, ms); (steps, ms): for any number of views (-1)
            table = tuple((int(e[0]), int(e[1]), float(e[2])) if len(e) == 3
                          else (int(e[0]), -1, float(e[1])) for e in self.job_ms)
        except (TypeError, ValueError, IndexError):
            raise ValueError(f"job_ms must be (steps, views, wall ms) or (steps, wall ms), "
                             f"got {self.job_ms!r}") from None
        if any(k < 0 or v < -1 or not (math.isfinite(ms) and ms >= 0) for k, v, ms in table):
            raise ValueError(f"job_ms: steps >= 0, views >= 0 (or -1: any) and finite wall ms "
                             f">= 0, got {table}")
        object.__setattr__(self, "job_ms", tuple(sorted(table)))
        if self.pool_workers and self.carry not in POOL_CARRIES:
            raise ValueError(f"the pool's twin (pool_workers={self.pool_workers}) runs the "
                             f"carries {', '.join(POOL_CARRIES)}; {self.carry!r} trains between "
                             "jobs, which a simulated worker does not")
        if self.pool_workers and self.score_every != 1:
            raise ValueError(f"with pool_workers={self.pool_workers} every decision goes to the "
                             f"pool, which chooses what is rendered: score_every must be 1, "
                             f"got {self.score_every}")
        if self.scored_decisions < 1:
            raise ValueError("the scored span holds no decision: raise scored_ms")

    def compute_ms(self, steps: int, views: int | None = None) -> float:
        """Scene ms a reconstruction of ``steps`` training steps (on ``views`` frames) takes at
        the run's ``time_scale``: ``job_ms``'s wall ms for that step count where it has it (a
        measured table: a cold start's steps cost more each than a warm start's, and a job of
        more frames more) — that of ``views`` frames, else the line through that step count's
        entries over their frames — else (``compute_fixed_ms`` + ``compute_step_ms`` · steps)
        wall ms; times the scale (the live clock: scene = wall × time_scale). What the virtual
        clock charges a scored decision before it is shown."""
        return self._job_wall_ms(steps, views) * self.time_scale

    def _job_wall_ms(self, steps: int, views: int | None) -> float:
        rows = [(v, ms) for k, v, ms in self.job_ms if k == steps]
        exact = [ms for v, ms in rows if views is not None and v == views]
        if exact:
            return exact[0]
        known = [(v, ms) for v, ms in rows if v >= 0]
        if views is not None and len({v for v, _ in known}) >= 2:
            mv = sum(v for v, _ in known) / len(known)
            mm = sum(ms for _, ms in known) / len(known)
            slope = (sum((v - mv) * (ms - mm) for v, ms in known)
                     / sum((v - mv) ** 2 for v, _ in known))
            return max(0.0, mm + slope * (views - mv))
        if rows:
            return sum(ms for _, ms in rows) / len(rows)
        return self.compute_fixed_ms + self.compute_step_ms * steps

    @property
    def end_ms(self) -> int:
        """First slot after the episode's last decision epoch."""
        return self.warmup_ms + self.scored_ms

    def decision_times_ms(self) -> list[int]:
        """Decision epochs t = k·period + offset in (0, end_ms), k ≥ 0."""
        start = self.decision_offset_ms if self.decision_offset_ms > 0 else self.decision_period_ms
        return list(range(start, self.end_ms, self.decision_period_ms))

    @property
    def scored_decisions(self) -> int:
        """How many decisions are scored per episode."""
        span = [t for t in self.decision_times_ms() if t >= self.warmup_ms]
        return math.ceil(len(span) / self.score_every)

    def with_(self, **changes: Any) -> EpisodeConfig:
        """A copy with ``changes`` (validated)."""
        return replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["field"] = dict(self.field)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EpisodeConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown episode config key(s) {unknown}; known: {sorted(known)}")
        return cls(**data)


@dataclass(frozen=True)
class Preset:
    """A named budget: the episode config and the sweep sizes of each command.

    ``gammas_ms``: the MAT thresholds Γ of ``tradeoff``; ``seeds``: S independent simulations
    per point; ``delays``: the delay specs of ``delay``; ``view_gammas_ms``: the Γ shown by
    ``views``; ``compare``: the policies of ``compare`` (``mat:best`` is replaced by the best Γ
    of the tradeoff when one is known).
    """

    name: str
    episode: EpisodeConfig
    gammas_ms: tuple[int, ...]
    seeds: int
    delays: tuple[str, ...]
    delay_gammas_ms: tuple[int, ...]
    delay_seeds: int
    view_gammas_ms: tuple[int, ...]
    compare: tuple[str, ...]
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["episode"] = self.episode.to_dict()
        return out


_QUICK_EPISODE = EpisodeConfig(
    carry="fresh",
    steps_per_epoch=300,
    warmup_ms=900,
    scored_ms=1200,
    score_every=10,
)
_PAPER_EPISODE = EpisodeConfig(
    carry="fresh",
    steps_per_epoch=1000,
    warmup_ms=900,
    scored_ms=2400,
    score_every=10,
)
_TEN_MS = tuple(range(0, 181, 10))

PRESETS: dict[str, Preset] = {
    "quick": Preset(
        name="quick",
        episode=_QUICK_EPISODE,
        gammas_ms=(0, 40, 70, 100, 130, 160),
        seeds=3,
        delays=("exp:20", "exp:60", "exp:100"),
        delay_gammas_ms=(40, 70, 100, 130, 160),
        delay_seeds=2,
        view_gammas_ms=(40, 70, 160),
        compare=("all", "mat:best", "freshest:6", "wait:40"),
        note="≤ 10 min per command on 2 CPU cores (4 scored decisions × 300 steps per "
             "episode); the shape, not the last decimal",
    ),
    "paper": Preset(
        name="paper",
        episode=_PAPER_EPISODE,
        gammas_ms=_TEN_MS,
        seeds=40,
        delays=("exp:10", "exp:20", "exp:40", "exp:60", "exp:80", "exp:100", "exp:120"),
        delay_gammas_ms=(*_TEN_MS, 210, 240, 300),
        delay_seeds=20,
        view_gammas_ms=(40, 70, 100, 130),
        compare=("all", "mat:best", "freshest:6", "freshest:9", "wait:40", "wait:70"),
        note="Γ every 10 ms (0–180: the paper's 0–120 and beyond, where the optimum of "
             "this model lies), 40 simulations per point, 8 scored decisions × 1000 steps "
             "per episode: for a GPU or a cluster",
    ),
}


def get_preset(name: str) -> Preset:
    """The preset ``name``; ``ValueError`` listing the known ones."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}") from None
