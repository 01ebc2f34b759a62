"""How a model is carried from one decision to the next, and how a decision is rendered.

One object, :class:`Reconstruction`, used by the experiments' virtual clock
(:func:`aoi3d.experiment.episode.run_plan`) and by the live trainer service alike, so that a
carry mode means the same thing in both settings. A *decision* hands the model the frames a
policy selected (:meth:`Reconstruction.set_views`); *background* training runs between
decisions (:meth:`Reconstruction.train`); a *scored* decision is turned into a novel view by
:meth:`Reconstruction.render_decision`.

Carry modes:

- ``fresh`` — the paper's per-time reconstruction: each rendered decision gets a new model
  trained ``render_steps`` steps on exactly that decision's frames. Nothing is trained in
  the background (:meth:`train` is a no-op), so a scored render reflects only its decision
  and its quality is the reward of that decision alone (exact credit for online learning).
  The live trainer's default: the only mode that keeps the tradeoff on the rotor scene.
- ``warm`` — one model trained continuously on the decision in force (the training set is
  swapped, the model kept) and rendered as it is. Cheap, but the model lags and averages
  its frames over many decisions: on the rotor close-up the blades blur away and the
  freshness of the frames stops mattering (docs/experiments.md, "Which carry keeps the
  tradeoff live").
- ``fork`` — the warm model, continuously trained on the decision in force, is the *start*
  of each rendered decision's reconstruction: a copy of it (:meth:`FieldTrainer.fork`:
  weights, optimizer state and random stream) trains ``render_steps`` more steps on exactly
  that decision's frames, is rendered, and is dropped. The idea: the warm model holds what
  does not move, the copy's short run places the moving parts. Measured on the rotor scene
  at 100 steps it renders worse than ``fresh`` and shows no tradeoff (docs/experiments.md,
  "Which carry keeps the tradeoff live"); the render still carries the earlier decisions' influence.

:class:`RenderedDecision` is a render and what made it: the steps of its model, those spent
on its decision's frames alone, the last loss and the number of views.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import torch

from aoi3d.field.trainer import FieldTrainer, TrainView
from aoi3d.quality import dynamic_mask
from aoi3d.scene.camera import Camera

__all__ = ["BACKGROUND_MODES", "CARRY_MODES", "FINETUNE_MODES", "CarryMode", "Reconstruction",
           "RenderedDecision", "WarmStart", "changed_cells", "check_carry"]

CarryMode = Literal["fork", "fresh", "stream", "warm"]
"""A carry mode (see the module docstring): the one spelling of the four. :data:`CARRY_MODES`,
the experiments' config and the trainer service's setting and ``PUT /carry`` take them from
here."""
CARRY_MODES: tuple[CarryMode, ...] = get_args(CarryMode)
"""The carry modes, in the order they are listed."""
BACKGROUND_MODES: frozenset[CarryMode] = frozenset({"fork", "warm"})
"""The modes with one model per worker, trained on the decision in force between decisions
(:meth:`Reconstruction.train`) and carried from job to job."""
FINETUNE_MODES: frozenset[CarryMode] = frozenset({"fork", "stream"})
"""The modes whose render starts from a carried model and trains it ``render_steps`` more
steps on its decision's frames (``fresh`` trains a new model; ``warm`` trains none)."""


def check_carry(carry: str, render_steps: int) -> CarryMode:
    """``carry`` as a :data:`CarryMode`; ``ValueError`` for an unknown mode, or a render budget
    the mode needs but lacks."""
    if carry not in CARRY_MODES:
        raise ValueError(f"carry must be one of {', '.join(CARRY_MODES)}, got {carry!r}")
    if isinstance(render_steps, bool) or not isinstance(render_steps, int) or render_steps < 0:
        raise ValueError(f"render_steps must be an int >= 0, got {render_steps!r}")
    if carry != "warm" and render_steps < 1:
        raise ValueError(f"carry {carry!r} trains each rendered decision: render_steps must "
                         f"be >= 1, got {render_steps}")
    return carry  # narrowed to a CarryMode by the membership test above


@dataclass(frozen=True)
class WarmStart:
    """Settings of the ``stream`` carry (the streaming warm start, see the module).

    ``cold_steps``: the budget of a cold start (no model yet, or one too old: its decision
    more than ``max_gap_ms`` of scene time away from the new one's, either way, not counting
    the time its own job took — :meth:`Reconstruction.ready`: a cold start slower than the gap
    would otherwise leave its worker cold for good; a decision without a time is always
    cold). A warm start trains ``render_steps``: ``reset`` — the
    grid's vertices the change carve marks go back to their initial values (and their Adam
    moments to 0); ``focus`` — that share of each batch's rays comes from the changed pixels;
    ``hold`` — the carried model's step counter is set back to ``cold_steps − render_steps``
    first, so that its schedule (coarse-to-fine stage, ray step, empty-space skipping) stays
    the one a fresh reconstruction ends on; ``lr_scale`` multiplies the learning rates of a
    warm start's steps. The change of a view: its pixels whose colour moved by more than
    ``change_tau`` since the camera's last frame this model trained on, dilated by
    ``dilation_px`` (:func:`aoi3d.quality.dynamic_mask`).
    """

    cold_steps: int = 100
    max_gap_ms: float = 500.0
    reset: bool = False
    focus: float = 0.5
    hold: bool = True
    change_tau: float = 8.0 / 255.0
    dilation_px: int = 1
    lr_scale: float = 2.0

    def __post_init__(self) -> None:
        c = self.cold_steps
        if isinstance(c, bool) or not isinstance(c, int) or c < 1:
            raise ValueError(f"cold_steps must be an int >= 1, got {c!r}")
        if not (math.isfinite(self.max_gap_ms) and self.max_gap_ms >= 0):
            raise ValueError(f"max_gap_ms must be a finite number >= 0, got {self.max_gap_ms}")
        if not 0.0 <= self.focus <= 1.0:
            raise ValueError(f"focus must be in [0, 1], got {self.focus}")
        if not 0.0 <= self.change_tau < 1.0:
            raise ValueError(f"change_tau must be in [0, 1), got {self.change_tau}")
        if not (math.isfinite(self.lr_scale) and self.lr_scale > 0):
            raise ValueError(f"lr_scale must be a finite number > 0, got {self.lr_scale}")
        d = self.dilation_px
        if isinstance(d, bool) or not isinstance(d, int) or d < 0:
            raise ValueError(f"dilation_px must be an int >= 0, got {d!r}")


def changed_cells(points: torch.Tensor, changes: Sequence[tuple[Camera, np.ndarray]]
                  ) -> torch.Tensor:
    """Which world ``points`` (P, 3) the scene may have changed at, carved from the views'
    change masks ``changes`` ((camera, H×W bool), ...): a point changed when at least one view
    sees it (in front of the camera, inside its image) and every view that sees it sees a
    changed pixel there — the visual hull of the change (a point a view shows unchanged is
    unchanged, whatever the others say). Returns bool (P,) on the points' device."""
    pts = points.detach().cpu().numpy().astype(np.float64)
    seen = np.zeros(len(pts), dtype=bool)
    unchanged = np.zeros(len(pts), dtype=bool)
    for camera, mask in changes:
        uv, depth = camera.project(pts)
        with np.errstate(invalid="ignore"):
            u = np.floor(uv[:, 0])
            v = np.floor(uv[:, 1])
            inside = (depth > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        ui = u[inside].astype(np.int64)
        vi = v[inside].astype(np.int64)
        hit = np.asarray(mask, dtype=bool)[vi, ui]
        idx = np.flatnonzero(inside)
        seen[idx] = True
        unchanged[idx[~hit]] = True
    return torch.from_numpy(seen & ~unchanged).to(points.device)


_FRAMES_KEPT = 256  # last frames kept per camera by the stream carry (a rig of 256 cameras)


@dataclass(frozen=True)
class RenderedDecision:
    """A novel view and what it is made of.

    ``image``: float32 H×W×3 in [0, 1]; ``steps``: training steps of the model that rendered
    it (the warm model's plus the copy's, for ``fork``); ``render_steps``: those spent on this
    decision's frames alone (0 for ``warm``); ``loss``: the last of those steps' photometric
    loss (NaN when none); ``n_views``: frames it trained on last.
    """

    image: np.ndarray
    steps: int
    render_steps: int
    loss: float
    n_views: int
    warm: bool = False
    """Started from the previous decision's model (the ``stream`` carry's warm start)."""


class Reconstruction:
    """A :class:`FieldTrainer` driven by a carry mode (see the module docstring).

    ``render_steps``: the budget of a rendered decision in ``fresh`` and ``fork`` (ignored by
    ``warm``).
    """

    def __init__(self, trainer: FieldTrainer, carry: str, render_steps: int,
                 warm_start: WarmStart | None = None) -> None:
        self.carry = check_carry(carry, render_steps)
        self.trainer = trainer
        self.render_steps = int(render_steps)
        self.warm_start = warm_start or WarmStart()
        self._views: list[TrainView] = []
        # the stream carry: the scene time of the model's last decision (None: no model yet)
        # and, per camera, the last frame the model trained on
        self._model_time_ms: float | None = None
        self._job_ms = 0.0  # scene ms its last job took (ready), not counted in the gap
        self._frames: OrderedDict[Camera, np.ndarray] = OrderedDict()
        # warm and fork: the scene time the trainer's model stands for (None: not known)
        self._time_ms: float | None = None
        self._rendered: FieldTrainer = trainer  # the model of the last render

    @property
    def trains_in_background(self) -> bool:
        """Whether :meth:`train` does anything (``warm`` and ``fork``)."""
        return self.carry in BACKGROUND_MODES

    def set_views(self, views: Sequence[TrainView], time_ms: float | None = None) -> None:
        """A new decision is in force: its frames are what the model trains on from now on.
        ``time_ms``: the decision's scene time; ``warm`` and ``fork`` carry their model there
        from the previous decision's (``FieldTrainer.advance``: a time-aware field moves along
        its motion; a static one is unchanged)."""
        views = list(views)
        if self.trains_in_background and time_ms is not None and math.isfinite(time_ms):
            if self._time_ms is not None:
                self.trainer.advance(time_ms - self._time_ms)
            self._time_ms = float(time_ms)
        self.trainer.set_views(views)  # checks them (and caches their rays) in every mode
        self._views = views

    def train(self, n: int) -> float:
        """``n`` background steps on the decision in force (no-op for ``fresh``); the last
        step's photometric loss, NaN when nothing trained."""
        if not self.trains_in_background or not self._views:
            return math.nan
        return self.trainer.step(n)

    def render_decision(self, camera: Camera, views: Sequence[TrainView] | None = None,
                        time_ms: float | None = None) -> RenderedDecision:
        """The novel view from ``camera`` for the decision whose frames are ``views``
        (default: the decision in force), taken at scene time ``time_ms`` (the ``stream``
        carry's age check; the others ignore it).

        ``warm`` renders the model as it is; ``fresh`` resets the model and trains it
        ``render_steps`` steps on ``views``; ``fork`` trains a copy of the warm model
        ``render_steps`` steps on ``views`` (the warm model is untouched); ``stream`` starts
        from its previous decision's model when it is recent enough (:class:`WarmStart`),
        else fresh with the cold budget. An empty selection trains nothing: the render shows
        the start (untrained for ``fresh``).
        """
        views = self._views if views is None else list(views)
        if self.carry == "stream":
            return self._stream(camera, views, time_ms)
        if self.carry == "warm":
            t = self._rendered = self.trainer
            return RenderedDecision(t.render(camera), t.steps, 0, math.nan, t.n_views)
        if self.carry == "fresh":
            model = self.trainer
            model.reset()
        else:
            model = self.trainer.fork()
        self._rendered = model
        model.set_views(views)
        loss = model.step(self.render_steps) if views else math.nan
        image = model.render(camera)
        return RenderedDecision(image, model.steps, self.render_steps if views else 0,
                                float(loss), len(views))

    def render_at(self, camera: Camera, ahead_ms: float) -> np.ndarray:
        """The model of the last :meth:`render_decision` rendered ``ahead_ms`` after its
        decision's time (the display time): a time-aware field shows the scene then, a static
        one the same image again (``FieldTrainer.render``)."""
        return self._rendered.render(camera, ahead_ms=ahead_ms)

    def ready(self, time_ms: float) -> None:
        """The last :meth:`render_decision` was ready (shown) at scene time ``time_ms``: the
        ``stream`` carry does not count the time its job took in the gap to the next decision
        (:meth:`is_warm`; no call: all of it counts)."""
        last = self._model_time_ms
        self._job_ms = max(0.0, time_ms - last) if last is not None and math.isfinite(
            time_ms) else 0.0

    def is_warm(self, time_ms: float | None) -> bool:
        """Whether a ``stream`` decision at scene time ``time_ms`` starts warm: a model exists
        and its last decision is at most ``max_gap_ms`` away, not counting the time its job
        took (:meth:`ready`)."""
        last = self._model_time_ms
        return (last is not None and time_ms is not None and math.isfinite(time_ms)
                and abs(time_ms - last) <= self.warm_start.max_gap_ms + self._job_ms)

    def _changes(self, views: Sequence[TrainView]) -> list[tuple[Camera, np.ndarray]]:
        """Each view's change mask against its camera's last frame (views of a camera the
        model has not trained on have none)."""
        ws = self.warm_start
        out = []
        for v in views:
            before = self._frames.get(v.camera)
            if before is not None:
                out.append((v.camera, dynamic_mask(_unit(v.image), [before], tau=ws.change_tau,
                                                   dilation_px=ws.dilation_px)))
        return out

    def _stream(self, camera: Camera, views: list[TrainView],
                time_ms: float | None) -> RenderedDecision:
        ws = self.warm_start
        model = self._rendered = self.trainer
        warm = self.is_warm(time_ms) and bool(views)
        if warm:
            assert time_ms is not None and self._model_time_ms is not None
            model.advance(time_ms - self._model_time_ms)  # a time-aware field moves along
            changes = self._changes(views)
            model.set_views(views)
            if ws.reset and changes:
                model.forget(lambda points: changed_cells(points, changes))
            if ws.focus > 0 and changes:
                by_camera = dict(changes)
                offset, parts = 0, []
                for v in views:
                    mask = by_camera.get(v.camera)
                    if mask is not None:
                        parts.append(torch.from_numpy(np.flatnonzero(mask.reshape(-1))) + offset)
                    offset += v.camera.width * v.camera.height
                model.set_focus(torch.cat(parts) if parts else None, ws.focus)
            if ws.hold:
                model.set_schedule_step(max(0, ws.cold_steps - self.render_steps))
            budget = self.render_steps
        else:
            model.reset()
            model.set_views(views)
            self._frames.clear()
            budget = ws.cold_steps
        if not views:
            loss = math.nan
        elif warm and ws.lr_scale != 1.0:
            with model.lr_scaled(ws.lr_scale):
                loss = model.step(budget)
        else:
            loss = model.step(budget)
        image = model.render(camera)
        for v in views:
            self._frames[v.camera] = _unit(v.image)
            self._frames.move_to_end(v.camera)
        while len(self._frames) > _FRAMES_KEPT:
            self._frames.popitem(last=False)
        self._model_time_ms = time_ms if views else None
        self._job_ms = 0.0
        return RenderedDecision(image, model.steps, budget if views else 0, float(loss),
                                len(views), warm)

    def set_carry(self, carry: str, render_steps: int) -> None:
        """Render with ``carry`` and ``render_steps`` from now on (model and views kept);
        ``ValueError`` — nothing changed — for an unknown mode or budget."""
        mode = check_carry(carry, render_steps)
        if mode != self.carry:
            self._model_time_ms = None  # the stream carry starts cold after a switch
            self._time_ms = None
        self.carry = mode
        self.render_steps = int(render_steps)


def _unit(image: np.ndarray) -> np.ndarray:
    """An image as float32 H×W×3 in [0, 1] (uint8 divided by 255)."""
    arr = np.asarray(image)
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    return arr.astype(np.float32, copy=False)
