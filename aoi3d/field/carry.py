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
  freshness of the frames stops mattering (docs/experiments.md, "The live carry").
- ``fork`` — the warm model, continuously trained on the decision in force, is the *start*
  of each rendered decision's reconstruction: a copy of it (:meth:`FieldTrainer.fork`:
  weights, optimizer state and random stream) trains ``render_steps`` more steps on exactly
  that decision's frames, is rendered, and is dropped. The idea: the warm model holds what
  does not move, the copy's short run places the moving parts. Measured on the rotor scene
  at 100 steps it renders worse than ``fresh`` and shows no tradeoff (docs/experiments.md,
  "The live carry"); the render still carries the earlier decisions' influence.

:class:`RenderedDecision` is a render and what made it: the steps of its model, those spent
on its decision's frames alone, the last loss and the number of views.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aoi3d.field.trainer import FieldTrainer, TrainView
from aoi3d.scene.camera import Camera

__all__ = ["CARRY_MODES", "Reconstruction", "RenderedDecision", "check_carry"]

CARRY_MODES = ("fork", "fresh", "warm")
"""The carry modes, see the module docstring."""


def check_carry(carry: str, render_steps: int) -> None:
    """Raise ``ValueError`` for an unknown mode, or a render budget the mode needs but lacks."""
    if carry not in CARRY_MODES:
        raise ValueError(f"carry must be one of {', '.join(CARRY_MODES)}, got {carry!r}")
    if isinstance(render_steps, bool) or not isinstance(render_steps, int) or render_steps < 0:
        raise ValueError(f"render_steps must be an int >= 0, got {render_steps!r}")
    if carry in ("fresh", "fork") and render_steps < 1:
        raise ValueError(f"carry {carry!r} trains each rendered decision: render_steps must "
                         f"be >= 1, got {render_steps}")


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


class Reconstruction:
    """A :class:`FieldTrainer` driven by a carry mode (see the module docstring).

    ``render_steps``: the budget of a rendered decision in ``fresh`` and ``fork`` (ignored by
    ``warm``).
    """

    def __init__(self, trainer: FieldTrainer, carry: str, render_steps: int) -> None:
        check_carry(carry, render_steps)
        self.trainer = trainer
        self.carry = carry
        self.render_steps = int(render_steps)
        self._views: list[TrainView] = []

    @property
    def trains_in_background(self) -> bool:
        """Whether :meth:`train` does anything (``warm`` and ``fork``)."""
        return self.carry != "fresh"

    def set_views(self, views: Sequence[TrainView]) -> None:
        """A new decision is in force: its frames are what the model trains on from now on."""
        views = list(views)
        self.trainer.set_views(views)  # checks them (and caches their rays) in every mode
        self._views = views

    def train(self, n: int) -> float:
        """``n`` background steps on the decision in force (no-op for ``fresh``); the last
        step's photometric loss, NaN when nothing trained."""
        if not self.trains_in_background or not self._views:
            return math.nan
        return self.trainer.step(n)

    def render_decision(self, camera: Camera,
                        views: Sequence[TrainView] | None = None) -> RenderedDecision:
        """The novel view from ``camera`` for the decision whose frames are ``views``
        (default: the decision in force).

        ``warm`` renders the model as it is; ``fresh`` resets the model and trains it
        ``render_steps`` steps on ``views``; ``fork`` trains a copy of the warm model
        ``render_steps`` steps on ``views`` (the warm model is untouched). An empty selection
        trains nothing: the render shows the start (untrained for ``fresh``).
        """
        views = self._views if views is None else list(views)
        if self.carry == "warm":
            t = self.trainer
            return RenderedDecision(t.render(camera), t.steps, 0, math.nan, t.n_views)
        if self.carry == "fresh":
            model = self.trainer
            model.reset()
        else:
            model = self.trainer.fork()
        model.set_views(views)
        loss = model.step(self.render_steps) if views else math.nan
        image = model.render(camera)
        return RenderedDecision(image, model.steps, self.render_steps if views else 0,
                                float(loss), len(views))

    def set_carry(self, carry: str, render_steps: int) -> None:
        """Render with ``carry`` and ``render_steps`` from now on (model and views kept);
        ``ValueError`` — nothing changed — for an unknown mode or budget."""
        check_carry(carry, render_steps)
        self.carry = carry
        self.render_steps = int(render_steps)
