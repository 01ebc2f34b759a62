"""Rule-based selection policies: all, MAT (maximum acceptable AoI Γ) and freshest-k."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from aoi3d.numbers import format_number
from aoi3d.policy.base import (
    BasePolicy,
    PolicyKind,
    PolicySpecError,
    as_aoi_vector,
    expect_fields,
    expect_keys,
    integer,
    number,
)


@dataclass(frozen=True)
class AllPolicy(BasePolicy):
    """Use every camera whose AoI is known."""

    kind: ClassVar[str] = "all"

    @property
    def spec(self) -> str:
        return "all"

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        known: np.ndarray = ~np.isnan(as_aoi_vector(aoi_ms))
        return known

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind}


@dataclass(frozen=True)
class MatPolicy(BasePolicy):
    """MAT: use camera n iff Δ_n(t) < Γ (``mat_ms``). Γ = 0 selects none."""

    mat_ms: float
    kind: ClassVar[str] = "mat"

    def __post_init__(self) -> None:
        value = number("mat_ms", self.mat_ms, minimum=0.0)
        object.__setattr__(self, "mat_ms", value)

    @property
    def spec(self) -> str:
        return f"mat:{format_number(self.mat_ms)}"

    @property
    def gamma_ms(self) -> float:
        """Γ: the rule's threshold."""
        return self.mat_ms

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        return as_aoi_vector(aoi_ms) < self.mat_ms  # NaN compares False: never selected

    def to_json(self) -> dict[str, Any]:
        value = int(self.mat_ms) if self.mat_ms.is_integer() else self.mat_ms
        return {"kind": self.kind, "mat_ms": value}


@dataclass(frozen=True)
class FreshestPolicy(BasePolicy):
    """Use the k cameras with the smallest known AoIs (ties: lower position first)."""

    k: int
    kind: ClassVar[str] = "freshest"

    def __post_init__(self) -> None:
        object.__setattr__(self, "k", integer("freshest k", self.k, minimum=0))

    @property
    def spec(self) -> str:
        return f"freshest:{self.k}"

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        aoi = as_aoi_vector(aoi_ms)
        n_known = int(np.count_nonzero(~np.isnan(aoi)))
        order = np.argsort(aoi, kind="stable")  # NaN sorts last
        mask = np.zeros(len(aoi), dtype=bool)
        mask[order[: min(self.k, n_known)]] = True
        return mask

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "k": self.k}

    def check_fits(self, n_cameras: int) -> None:
        """k must not exceed the rig's N cameras."""
        if not 0 <= self.k <= n_cameras:
            raise PolicySpecError(f"freshest k must be in 0..{n_cameras} (the training "
                                  f"cameras), got {self.k}", self.to_json())


def _all_from_args(fields: list[str]) -> AllPolicy:
    expect_fields("all", fields, ())
    return AllPolicy()


def _all_from_json(params: Mapping[str, Any]) -> AllPolicy:
    expect_keys("all", params, ())
    return AllPolicy()


def _mat_from_args(fields: list[str]) -> MatPolicy:
    (value,) = expect_fields("mat", fields, ("ms",))
    return MatPolicy(number("mat_ms", value, minimum=0.0))


def _mat_from_json(params: Mapping[str, Any]) -> MatPolicy:
    expect_keys("mat", params, ("mat_ms",))
    if isinstance(params["mat_ms"], str):
        raise PolicySpecError(f"mat_ms must be a JSON number, got {params['mat_ms']!r}")
    return MatPolicy(params["mat_ms"])


def _freshest_from_args(fields: list[str]) -> FreshestPolicy:
    (value,) = expect_fields("freshest", fields, ("k",))
    return FreshestPolicy(integer("freshest k", value, minimum=0))


def _freshest_from_json(params: Mapping[str, Any]) -> FreshestPolicy:
    expect_keys("freshest", params, ("k",))
    if isinstance(params["k"], str):
        raise PolicySpecError(f"freshest k must be a JSON number, got {params['k']!r}")
    return FreshestPolicy(params["k"])


KINDS = (
    PolicyKind("all", "all", _all_from_args, _all_from_json, family="rule"),
    PolicyKind("mat", "mat:<ms>", _mat_from_args, _mat_from_json, family="rule"),
    PolicyKind("freshest", "freshest:<k>", _freshest_from_args, _freshest_from_json,
               family="rule"),
)
"""The rule kinds, registered by :mod:`aoi3d.policy`."""
