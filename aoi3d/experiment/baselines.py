"""The follow-up paper's two baselines (arXiv 2509.17282) as trainer options of an episode.

Both change how the radiance field learns from the frames a policy selected, not which
frames it selects; they are meant to take every frame (``all``) and let the model, not the
scheduler, deal with their age:

- ``tembed[:<features>[:<scale_ms>]]`` — **timeliness embedding**: the field takes each
  training image's age (its AoI at the decision) as an input, a Fourier embedding of the age
  with ``features`` terms over ``scale_ms`` that scales a residual grid
  (``GridConfig.age_features`` / ``age_scale_ms``, :mod:`aoi3d.field.grid`); the novel view
  is rendered at age 0. Default ``tembed:2:300``. Grid backend only.
- ``wsum:<tau_ms>`` — **weighted sum**: the training loss weights each image by
  exp(−age/τ), normalised over the batch (``FieldConfig.age_weight_tau_ms``,
  :mod:`aoi3d.field.trainer`). Any backend.

A compare spec pairs a trainer option with a policy: ``<trainer>[@<policy>]`` (the policy
defaults to ``all``), e.g. ``wsum:60``, ``tembed``, ``wsum:60@mat:130``. Its label is the
canonical ``<trainer>`` when the policy is ``all``, else ``<trainer>@<policy>``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from aoi3d.numbers import format_number

__all__ = [
    "TRAINER_FORMS",
    "TRAINER_KINDS",
    "TrainerOption",
    "TrainerSpecError",
    "baseline_label",
    "is_trainer_spec",
    "parse_trainer",
    "split_baseline",
]

TRAINER_KINDS = ("tembed", "wsum")
TRAINER_FORMS = ("tembed[:<features>[:<scale_ms>]]", "wsum:<tau_ms>")
"""The accepted forms, as error messages list them."""


class TrainerSpecError(ValueError):
    """A trainer option spec is invalid; the message lists the accepted forms."""

    def __init__(self, problem: str, spec: object) -> None:
        super().__init__(f"bad trainer option {spec!r}: {problem}. Accepted forms: "
                         f"{', '.join(TRAINER_FORMS)}, each optionally @<policy> "
                         "(default @all).")


@dataclass(frozen=True)
class TrainerOption:
    """One baseline: ``kind`` (``tembed`` or ``wsum``) and its parameters."""

    kind: str
    features: int = 0
    scale_ms: float = 0.0
    tau_ms: float = 0.0

    @property
    def spec(self) -> str:
        """The canonical text: ``tembed:<features>:<scale_ms>`` or ``wsum:<tau_ms>``."""
        if self.kind == "tembed":
            return f"tembed:{self.features}:{format_number(self.scale_ms)}"
        return f"wsum:{format_number(self.tau_ms)}"

    def field_overrides(self) -> dict[str, Any]:
        """The field config settings this option sets (merged over the episode's)."""
        if self.kind == "tembed":
            return {"age_features": self.features, "age_scale_ms": self.scale_ms}
        return {"age_weight_tau_ms": self.tau_ms}


def _positive(name: str, text: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise TrainerSpecError(f"{name} must be a number, got {text!r}", spec) from None
    if not math.isfinite(value) or value <= 0:
        raise TrainerSpecError(f"{name} must be a finite number > 0, got {text!r}", spec)
    return value


def is_trainer_spec(spec: str) -> bool:
    """Whether ``spec`` names a trainer option (its first field is one of the kinds)."""
    head = spec.strip().split("@", 1)[0].split(":", 1)[0].strip().lower()
    return head in TRAINER_KINDS


def parse_trainer(spec: str) -> TrainerOption:
    """A trainer option from its spec (no ``@<policy>``); ``TrainerSpecError`` otherwise."""
    kind, *fields = (f.strip() for f in spec.strip().split(":"))
    kind = kind.lower()
    if kind == "tembed":
        if len(fields) > 2:
            raise TrainerSpecError(f"tembed takes at most 2 parameters, got {len(fields)}",
                                   spec)
        features = 2
        if fields:
            try:
                features = int(fields[0])
            except ValueError:
                raise TrainerSpecError(f"features must be a whole number, got {fields[0]!r}",
                                       spec) from None
            if features < 1:
                raise TrainerSpecError(f"features must be >= 1, got {features}", spec)
        scale = _positive("scale_ms", fields[1], spec) if len(fields) == 2 else 300.0
        return TrainerOption("tembed", features=features, scale_ms=scale)
    if kind == "wsum":
        if len(fields) != 1:
            raise TrainerSpecError(f"wsum takes 1 parameter (wsum:<tau_ms>), got {len(fields)}",
                                   spec)
        return TrainerOption("wsum", tau_ms=_positive("tau_ms", fields[0], spec))
    raise TrainerSpecError(f"unknown trainer option {kind!r}", spec)


def split_baseline(spec: str) -> tuple[TrainerOption, str]:
    """``<trainer>[@<policy>]`` → the trainer option and the policy's spec (``all`` when
    none is given; the policy is not parsed here)."""
    trainer, sep, policy = spec.strip().partition("@")
    policy = policy.strip()
    if sep and not policy:
        raise TrainerSpecError("a policy must follow '@'", spec)
    return parse_trainer(trainer), policy or "all"


def baseline_label(option: TrainerOption, policy: str) -> str:
    """How results name a baseline run: the option's spec, with ``@<policy>`` unless the
    policy is ``all``."""
    return option.spec if policy == "all" else f"{option.spec}@{policy}"
