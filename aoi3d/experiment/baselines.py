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
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from aoi3d.numbers import format_number
from aoi3d.policy import PolicyKind, PolicySpecError, kind_of, register_policy

__all__ = [
    "KINDS",
    "TRAINER_FORMS",
    "TRAINER_KINDS",
    "TimelinessEmbedding",
    "TrainerOption",
    "TrainerSpecError",
    "WeightedSum",
    "baseline_label",
    "is_trainer_spec",
    "parse_trainer",
    "split_baseline",
]


class TrainerSpecError(ValueError):
    """A trainer option spec is invalid; the message lists the accepted forms."""

    def __init__(self, problem: str, spec: object) -> None:
        super().__init__(f"bad trainer option {spec!r}: {problem}. Accepted forms: "
                         f"{', '.join(TRAINER_FORMS)}, each optionally @<policy> "
                         "(default @all).")


@dataclass(frozen=True)
class TimelinessEmbedding:
    """``tembed:<features>:<scale_ms>``: the field takes each image's age as an input."""

    features: int = 2
    scale_ms: float = 300.0
    kind: ClassVar[str] = "tembed"

    @property
    def spec(self) -> str:
        return f"tembed:{self.features}:{format_number(self.scale_ms)}"

    def field_overrides(self) -> dict[str, Any]:
        """The field config settings this option sets (merged over the episode's)."""
        return {"age_features": self.features, "age_scale_ms": self.scale_ms}

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "features": self.features, "scale_ms": self.scale_ms}


@dataclass(frozen=True)
class WeightedSum:
    """``wsum:<tau_ms>``: the loss weights each image by exp(−age/τ)."""

    tau_ms: float
    kind: ClassVar[str] = "wsum"

    @property
    def spec(self) -> str:
        return f"wsum:{format_number(self.tau_ms)}"

    def field_overrides(self) -> dict[str, Any]:
        """The field config settings this option sets (merged over the episode's)."""
        return {"age_weight_tau_ms": self.tau_ms}

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "tau_ms": self.tau_ms}


TrainerOption = TimelinessEmbedding | WeightedSum
"""One baseline: its ``kind``, ``spec``, ``field_overrides()`` and ``to_json()``."""


def _positive(name: str, value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise PolicySpecError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(x) or x <= 0:
        raise PolicySpecError(f"{name} must be a finite number > 0, got {value!r}")
    return x


def _tembed_from_args(fields: list[str]) -> TimelinessEmbedding:
    if len(fields) > 2:
        raise PolicySpecError(f"tembed takes at most 2 parameters, got {len(fields)}")
    features = 2
    if fields:
        try:
            features = int(fields[0])
        except ValueError:
            raise PolicySpecError(f"features must be a whole number, got {fields[0]!r}"
                                  ) from None
        if features < 1:
            raise PolicySpecError(f"features must be >= 1, got {features}")
    scale = _positive("scale_ms", fields[1]) if len(fields) == 2 else 300.0
    return TimelinessEmbedding(features=features, scale_ms=scale)


def _tembed_from_json(params: Mapping[str, Any]) -> TimelinessEmbedding:
    return _tembed_from_args([str(params.get("features", 2)), str(params.get("scale_ms", 300.0))])


def _wsum_from_args(fields: list[str]) -> WeightedSum:
    if len(fields) != 1:
        raise PolicySpecError(f"wsum takes 1 parameter (wsum:<tau_ms>), got {len(fields)}")
    return WeightedSum(_positive("tau_ms", fields[0]))


def _wsum_from_json(params: Mapping[str, Any]) -> WeightedSum:
    return WeightedSum(_positive("tau_ms", params.get("tau_ms")))


KINDS = (
    PolicyKind("tembed", "tembed[:<features>[:<scale_ms>]]", _tembed_from_args,
               _tembed_from_json, family="baseline"),
    PolicyKind("wsum", "wsum:<tau_ms>", _wsum_from_args, _wsum_from_json, family="baseline"),
)
"""The baseline kinds, registered (family ``baseline``) when this module is imported."""
for _kind in KINDS:
    register_policy(_kind)
del _kind
TRAINER_KINDS = tuple(k.kind for k in KINDS)
TRAINER_FORMS = tuple(k.form for k in KINDS)
"""The accepted forms, as error messages list them."""


def is_trainer_spec(spec: str) -> bool:
    """Whether ``spec`` names a trainer option (its kind is of the ``baseline`` family)."""
    try:
        return kind_of(spec).family == "baseline"
    except PolicySpecError:
        return False


def parse_trainer(spec: str) -> TrainerOption:
    """A trainer option from its spec (no ``@<policy>``); ``TrainerSpecError`` otherwise."""
    kind, *fields = (f.strip() for f in spec.strip().split(":"))
    if not is_trainer_spec(kind):
        raise TrainerSpecError(f"unknown trainer option {kind.lower()!r}", spec)
    try:
        return kind_of(kind).from_args(fields)
    except PolicySpecError as err:
        raise TrainerSpecError(err.problem, spec) from None


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
