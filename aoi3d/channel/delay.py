"""Transmission-delay distributions of the camera uplinks, and the slot rule.

A delay spec names a distribution of the transmission time Y in milliseconds:

- ``exp:MEAN`` — exponential with mean MEAN (> 0);
- ``const:D`` — always D (>= 0);
- ``uniform:LO:HI`` — uniform on [LO, HI] (0 <= LO <= HI);
- ``gamma:K:THETA`` — gamma with shape K (> 0) and scale THETA (> 0), mean K·THETA;
- ``lognormal:MU:SIGMA`` — ln Y is normal with mean MU and standard deviation SIGMA (> 0).

Time is slotted (T_s = 1 ms): a frame entering its link at slot g is delivered at slot
``g + delay_slots(Y)`` with ``delay_slots(Y) = max(1, ceil(Y))``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, overload

import numpy as np
from scipy import special

from aoi3d.numbers import format_number

ACCEPTED_FORMS: tuple[str, ...] = (
    "exp:MEAN",
    "const:D",
    "uniform:LO:HI",
    "gamma:K:THETA",
    "lognormal:MU:SIGMA",
)
_FORMS_NOTE = "values in ms; lognormal's MU and SIGMA are of ln Y"


MAX_MEAN_DELAY_MS = 60_000.0
"""The largest mean delay a spec may have (60 s of sim time)."""
MAX_DELAY_MS = 60_000.0
"""Sampled delays are capped here (:func:`delay_slots`): no frame holds a link longer, so no
distribution — however heavy its tail — can block a link for good."""


class DelaySpecError(ValueError):
    """A delay spec (or distribution parameter) is invalid; the message lists the accepted forms."""

    def __init__(self, problem: str, spec: str | None = None) -> None:
        where = f"bad delay spec {spec!r}: " if spec is not None else "bad delay: "
        forms = ", ".join(ACCEPTED_FORMS)
        super().__init__(f"{where}{problem}. Accepted forms: {forms} ({_FORMS_NOTE}).")
        self.problem = problem
        self.spec = spec


@overload
def delay_slots(y_ms: float) -> int: ...
@overload
def delay_slots(y_ms: np.ndarray) -> np.ndarray: ...
def delay_slots(y_ms: float | np.ndarray) -> int | np.ndarray:
    """Slots a frame spends on the link: ``min(MAX_DELAY_MS, max(1, ceil(Y)))`` (int, or an
    int64 array)."""
    if np.ndim(y_ms) == 0:
        y = float(y_ms)
        if not math.isfinite(y):
            raise ValueError(f"delay must be finite, got {y}")
        return int(min(MAX_DELAY_MS, max(1, math.ceil(y))))
    y_arr = np.asarray(y_ms, dtype=np.float64)
    if not np.all(np.isfinite(y_arr)):
        raise ValueError("delays must be finite")
    return np.clip(np.ceil(y_arr), 1.0, MAX_DELAY_MS).astype(np.int64)


class DelayDistribution(ABC):
    """A distribution of the transmission time Y (ms) of one frame over one link."""

    kind: ClassVar[str]

    @property
    @abstractmethod
    def params(self) -> tuple[float, ...]:
        """The spec's numbers, in spec order."""

    @property
    def spec(self) -> str:
        """Canonical spec, e.g. ``exp:60``; ``parse_delay(d.spec) == d``."""
        return ":".join([self.kind, *(format_number(p) for p in self.params)])

    if TYPE_CHECKING:
        @property
        def mean_ms(self) -> float:
            """E[Y] in ms (a field or a property of each distribution)."""
    else:
        #: E[Y] in ms (a field or a property of each distribution).
        mean_ms: float

    @abstractmethod
    def sample(self, rng: np.random.Generator, size: int = 1) -> np.ndarray:
        """``size`` independent draws (float64 ms). Draws are consumed one value at a time,
        so ``sample(rng, n)`` equals ``n`` calls of ``sample(rng, 1)`` on the same stream."""

    @abstractmethod
    def cdf(self, x_ms: float | np.ndarray) -> np.ndarray:
        """P(Y <= x) (float64 array shaped like ``x_ms``)."""

    @abstractmethod
    def ppf(self, q: float) -> float:
        """The q-quantile of Y in ms, 0 < q < 1."""

    def __str__(self) -> str:
        return self.spec

    @staticmethod
    def _check_size(size: int) -> int:
        if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 0:
            raise ValueError(f"size must be an int >= 0, got {size!r}")
        return int(size)

    @staticmethod
    def _check_q(q: float) -> float:
        if not 0.0 < q < 1.0:
            raise ValueError(f"quantile level must be in (0, 1), got {q}")
        return float(q)


_n = format_number


def _require(ok: bool, problem: str, dist: str) -> None:
    if not ok:
        raise DelaySpecError(problem, dist)


@dataclass(frozen=True)
class ExponentialDelay(DelayDistribution):
    mean_ms: float
    kind: ClassVar[str] = "exp"

    def __post_init__(self) -> None:
        _require(math.isfinite(self.mean_ms) and self.mean_ms > 0,
                 f"exp MEAN must be a finite number > 0, got {_n(self.mean_ms)}",
                 f"exp:{_n(self.mean_ms)}")

    @property
    def params(self) -> tuple[float, ...]:
        return (self.mean_ms,)

    def sample(self, rng: np.random.Generator, size: int = 1) -> np.ndarray:
        return rng.exponential(self.mean_ms, self._check_size(size))

    def cdf(self, x_ms: float | np.ndarray) -> np.ndarray:
        x = np.asarray(x_ms, dtype=np.float64)
        return np.where(x > 0, -np.expm1(-np.maximum(x, 0.0) / self.mean_ms), 0.0)

    def ppf(self, q: float) -> float:
        return float(-self.mean_ms * math.log1p(-self._check_q(q)))


@dataclass(frozen=True)
class ConstantDelay(DelayDistribution):
    delay_ms: float
    kind: ClassVar[str] = "const"

    def __post_init__(self) -> None:
        _require(math.isfinite(self.delay_ms) and self.delay_ms >= 0,
                 f"const D must be a finite number >= 0, got {_n(self.delay_ms)}",
                 f"const:{_n(self.delay_ms)}")

    @property
    def params(self) -> tuple[float, ...]:
        return (self.delay_ms,)

    @property
    def mean_ms(self) -> float:
        return float(self.delay_ms)

    def sample(self, rng: np.random.Generator, size: int = 1) -> np.ndarray:
        return np.full(self._check_size(size), float(self.delay_ms))

    def cdf(self, x_ms: float | np.ndarray) -> np.ndarray:
        return (np.asarray(x_ms, dtype=np.float64) >= self.delay_ms).astype(np.float64)

    def ppf(self, q: float) -> float:
        self._check_q(q)
        return float(self.delay_ms)


@dataclass(frozen=True)
class UniformDelay(DelayDistribution):
    low_ms: float
    high_ms: float
    kind: ClassVar[str] = "uniform"

    def __post_init__(self) -> None:
        spec = f"uniform:{_n(self.low_ms)}:{_n(self.high_ms)}"
        _require(math.isfinite(self.low_ms) and math.isfinite(self.high_ms),
                 "uniform LO and HI must be finite", spec)
        _require(self.low_ms >= 0, f"uniform LO must be >= 0, got {_n(self.low_ms)}", spec)
        _require(self.low_ms <= self.high_ms,
                 f"uniform LO must be <= HI, got LO={_n(self.low_ms)} > HI={_n(self.high_ms)}",
                 spec)

    @property
    def params(self) -> tuple[float, ...]:
        return (self.low_ms, self.high_ms)

    @property
    def mean_ms(self) -> float:
        return 0.5 * (self.low_ms + self.high_ms)

    def sample(self, rng: np.random.Generator, size: int = 1) -> np.ndarray:
        return rng.uniform(self.low_ms, self.high_ms, self._check_size(size))

    def cdf(self, x_ms: float | np.ndarray) -> np.ndarray:
        x = np.asarray(x_ms, dtype=np.float64)
        width = self.high_ms - self.low_ms
        if width == 0:
            return (x >= self.low_ms).astype(np.float64)
        return np.clip((x - self.low_ms) / width, 0.0, 1.0)

    def ppf(self, q: float) -> float:
        return float(self.low_ms + self._check_q(q) * (self.high_ms - self.low_ms))


@dataclass(frozen=True)
class GammaDelay(DelayDistribution):
    shape: float
    scale_ms: float
    kind: ClassVar[str] = "gamma"

    def __post_init__(self) -> None:
        spec = f"gamma:{_n(self.shape)}:{_n(self.scale_ms)}"
        _require(math.isfinite(self.shape) and self.shape > 0,
                 f"gamma K (shape) must be a finite number > 0, got {_n(self.shape)}", spec)
        _require(math.isfinite(self.scale_ms) and self.scale_ms > 0,
                 f"gamma THETA (scale, ms) must be a finite number > 0, got {_n(self.scale_ms)}",
                 spec)

    @property
    def params(self) -> tuple[float, ...]:
        return (self.shape, self.scale_ms)

    @property
    def mean_ms(self) -> float:
        return float(self.shape * self.scale_ms)

    def sample(self, rng: np.random.Generator, size: int = 1) -> np.ndarray:
        return rng.gamma(self.shape, self.scale_ms, self._check_size(size))

    def cdf(self, x_ms: float | np.ndarray) -> np.ndarray:
        x = np.asarray(x_ms, dtype=np.float64)
        return np.asarray(special.gammainc(self.shape, np.maximum(x, 0.0) / self.scale_ms))

    def ppf(self, q: float) -> float:
        return float(special.gammaincinv(self.shape, self._check_q(q)) * self.scale_ms)


@dataclass(frozen=True)
class LogNormalDelay(DelayDistribution):
    mu: float
    sigma: float
    kind: ClassVar[str] = "lognormal"

    def __post_init__(self) -> None:
        spec = f"lognormal:{_n(self.mu)}:{_n(self.sigma)}"
        _require(math.isfinite(self.mu), f"lognormal MU must be finite, got {_n(self.mu)}", spec)
        _require(math.isfinite(self.sigma) and self.sigma > 0,
                 f"lognormal SIGMA must be a finite number > 0, got {_n(self.sigma)}", spec)

    @property
    def params(self) -> tuple[float, ...]:
        return (self.mu, self.sigma)

    @property
    def mean_ms(self) -> float:
        return float(math.exp(self.mu + 0.5 * self.sigma**2))

    def sample(self, rng: np.random.Generator, size: int = 1) -> np.ndarray:
        return rng.lognormal(self.mu, self.sigma, self._check_size(size))

    def cdf(self, x_ms: float | np.ndarray) -> np.ndarray:
        x = np.asarray(x_ms, dtype=np.float64)
        with np.errstate(divide="ignore"):
            z = (np.log(np.maximum(x, 0.0)) - self.mu) / self.sigma
        return np.asarray(special.ndtr(z))

    def ppf(self, q: float) -> float:
        return float(math.exp(self.mu + self.sigma * special.ndtri(self._check_q(q))))


_KINDS: dict[str, tuple[type[DelayDistribution], tuple[str, ...]]] = {
    "exp": (ExponentialDelay, ("MEAN",)),
    "const": (ConstantDelay, ("D",)),
    "uniform": (UniformDelay, ("LO", "HI")),
    "gamma": (GammaDelay, ("K", "THETA")),
    "lognormal": (LogNormalDelay, ("MU", "SIGMA")),
}


def parse_delay(spec: str | DelayDistribution) -> DelayDistribution:
    """Parse ``exp:60``, ``const:40``, ``uniform:20:100``, ``gamma:K:THETA`` or
    ``lognormal:MU:SIGMA``; a distribution passes through unchanged.

    Raises ``DelaySpecError`` (a ``ValueError``) saying what is wrong and listing the forms.
    """
    if isinstance(spec, DelayDistribution):
        return spec
    if not isinstance(spec, str):
        raise DelaySpecError(f"expected a string, got {type(spec).__name__}", repr(spec))
    text = spec.strip()
    if not text:
        raise DelaySpecError("empty spec", spec)
    kind, *fields = (part.strip() for part in text.split(":"))
    kind = kind.lower()
    if kind not in _KINDS:
        raise DelaySpecError(f"unknown kind {kind!r}", spec)
    cls, names = _KINDS[kind]
    if len(fields) != len(names):
        form = ":".join([kind, *names])
        raise DelaySpecError(
            f"{kind} takes {len(names)} parameter(s) ({form}), got {len(fields)}", spec
        )
    values: list[float] = []
    for name, field in zip(names, fields, strict=True):
        try:
            value = float(field)
        except ValueError:
            raise DelaySpecError(f"{kind} {name} must be a number, got {field!r}", spec) from None
        if not math.isfinite(value):
            raise DelaySpecError(f"{kind} {name} must be finite, got {field!r}", spec)
        values.append(value)
    try:
        dist = cls(*values)
    except DelaySpecError as err:
        raise DelaySpecError(err.problem, spec) from None
    try:
        mean = dist.mean_ms
    except OverflowError:
        mean = math.inf
    if not mean <= MAX_MEAN_DELAY_MS:
        raise DelaySpecError(f"mean delay {format_number(mean)} ms exceeds the maximum of "
                             f"{format_number(MAX_MEAN_DELAY_MS)} ms", spec)
    return dist
