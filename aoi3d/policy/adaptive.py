"""Policies that adapt Γ to a changing channel (issue 32): the ``adaptive`` family.

Both apply the MAT rule (use camera n iff Δ_n < Γ) with a Γ that moves:

- ``adaptive:plugin[:<halflife_ms>]`` — the **plug-in** policy. It estimates the link's mean
  transmission time E[Y] online from the (delivery − generation) time of every frame the edge
  receives (a :class:`DelayEstimator`, exponentially forgetting with the given half-life of
  channel time, default 250 ms: chosen on the design traces, ``bench/adaptive_halflife.py``),
  and takes Γ = Γ*(Ê[Y]) from the measured curve of the best Γ against the mean delay
  (:class:`GammaCurve`, ``gamma_curve.json`` beside this module: the ``aoi3d experiment
  delay`` sweep that measured it, with its command). Before the first
  delivery Γ is the curve's value at its middle point.
- ``adaptive:bandit[:<window>]`` — a **sliding-window UCB bandit** over Γ arms
  (:class:`SlidingWindowUCB`, default arms 40, 70, 100, 130, 190, 280 ms), rewarded by the
  quality of the render its decision produced (PSNR in dB by default). The reward comes
  later than the decision — on the virtual clock when the episode has scored the decision
  (:func:`aoi3d.experiment.adaptive.run_stepwise`), live when the ``Quality`` of the render
  arrives on the ``quality`` topic — and is credited to the arm that decided for that time.
  The arm in force changes only when a reward has come in since it was chosen, so every arm
  choice gets its own reward.

What they see, beyond the AoI vector (the two optional questions of
:class:`aoi3d.policy.base.Policy` that every policy answers and these two use):

- ``observe(now_ms, deliveries)``: called by :func:`aoi3d.policy.decide.decide` at every
  decision, with the time s the decision is for and the frames delivered since the previous
  decision, each ``(camera index, generation ms, delivery ms)`` — the caller's, exactly as
  ``newest_at`` is: the simulated links on the virtual clock, the scheduler's tracker live.
- ``observe_quality(time_ms, scores)``: the scores of the render made for time ``time_ms``
  (``psnr_db``, ``reward``, …; only for a policy whose ``wants_quality`` is true).

Both are stateful: ``reset()`` starts a new episode. ``gamma_ms`` is the Γ in force, which
the scheduler reports with each decision (the console draws it over time).
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np

from aoi3d.metric import PSNR, PSNR_DYNAMIC, REWARD, SSIM, names_of
from aoi3d.numbers import format_number
from aoi3d.policy.base import (
    BasePolicy,
    PolicyKind,
    PolicySpecError,
    as_aoi_vector,
    integer,
    number,
)

__all__ = [
    "DEFAULT_ARMS_MS",
    "KIND",
    "BanditPolicy",
    "DelayEstimator",
    "GammaCurve",
    "PluginPolicy",
    "SlidingWindowUCB",
    "load_gamma_curve",
]

FAMILY = "adaptive"
"""The registry family of these kinds (:data:`aoi3d.policy.base.FAMILIES`): rules whose
parameter follows what they observe, declared by :mod:`aoi3d.policy` before it registers
:data:`KIND`."""

DEFAULT_HALFLIFE_MS = 250.0
"""Chosen on the design traces only (``bench/adaptive_halflife.py``: the smallest tracking
error of Γ against Γ* at the last second's mean delay, among 250 ms … 10 s)."""
DEFAULT_WINDOW = 24
DEFAULT_ARMS_MS: tuple[float, ...] = (40.0, 70.0, 100.0, 130.0, 190.0, 280.0)
DEFAULT_EXPLORE = 1.0
"""UCB exploration constant, in units of the reward (dB of PSNR by default)."""
QUALITY_METRICS = names_of((PSNR, REWARD, SSIM, PSNR_DYNAMIC))
"""What a bandit may maximise (all higher-is-better): the scores a live Quality carries for a
decision (:mod:`aoi3d.metric`)."""

Delivery = tuple[int, float, float]
"""``(camera index, generation ms, delivery ms)`` of one delivered frame."""


# ---------------------------------------------------------------------------- estimators
class DelayEstimator:
    """Online mean of the transmission time Y from delivered frames, forgetting the past
    exponentially in channel time: a sample delivered ``a`` ms before the newest one weighs
    2^(−a / ``halflife_ms``). Also keeps the last ``window`` samples for quantiles.

    The samples are the accepted frames' Y = delivery − generation; a frame dropped by a busy
    link is never seen, and a frame in flight is seen only when it lands (so a rise of the
    delay shows up after the slower frames arrive)."""

    def __init__(self, halflife_ms: float = DEFAULT_HALFLIFE_MS, window: int = 256) -> None:
        if not (math.isfinite(halflife_ms) and halflife_ms > 0):
            raise ValueError(f"halflife_ms must be > 0, got {halflife_ms!r}")
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window!r}")
        self.halflife_ms = float(halflife_ms)
        self._sum = 0.0
        self._weight = 0.0
        self._now = -math.inf
        self._recent: deque[float] = deque(maxlen=window)
        self.count = 0

    def observe(self, generation_ms: float, delivery_ms: float) -> None:
        """One delivered frame; a negative or non-finite delay is ignored."""
        y = float(delivery_ms) - float(generation_ms)
        if not (math.isfinite(y) and y >= 0):
            return
        t = float(delivery_ms)
        if t > self._now:
            if self._weight > 0:
                decay = 2.0 ** (-(t - self._now) / self.halflife_ms)
                self._sum *= decay
                self._weight *= decay
            self._now = t
            w = 1.0
        else:  # delivered before the newest one seen (another camera, a late report)
            w = 2.0 ** (-(self._now - t) / self.halflife_ms)
        self._sum += w * y
        self._weight += w
        self._recent.append(y)
        self.count += 1

    @property
    def mean_ms(self) -> float:
        """The forgetting mean of Y (ms); NaN before any sample."""
        return self._sum / self._weight if self._weight > 0 else math.nan

    def quantile(self, q: float) -> float:
        """The q-quantile of the last ``window`` samples (ms); NaN before any."""
        if not self._recent:
            return math.nan
        return float(np.quantile(np.fromiter(self._recent, dtype=np.float64), q))


@dataclass(frozen=True)
class GammaCurve:
    """Γ*(E[Y]): the best Γ against the mean delay, measured at points; piecewise linear in
    log E[Y] between them, flat beyond the ends."""

    mean_delay_ms: tuple[float, ...]
    gamma_ms: tuple[float, ...]
    source: str = ""

    def __post_init__(self) -> None:
        if len(self.mean_delay_ms) != len(self.gamma_ms) or not self.gamma_ms:
            raise ValueError("a Γ curve needs as many Γ as mean delays, at least one")
        order = np.argsort(self.mean_delay_ms)
        xs = tuple(float(self.mean_delay_ms[i]) for i in order)
        if any(x <= 0 for x in xs) or len(set(xs)) != len(xs):
            raise ValueError("the curve's mean delays must be distinct and > 0")
        object.__setattr__(self, "mean_delay_ms", xs)
        object.__setattr__(self, "gamma_ms", tuple(float(self.gamma_ms[i]) for i in order))

    def __call__(self, mean_delay_ms: float) -> float:
        """Γ* at the mean delay (the curve's middle point for NaN)."""
        if not math.isfinite(mean_delay_ms):
            return self.gamma_ms[len(self.gamma_ms) // 2]
        x = math.log(max(mean_delay_ms, 1e-3))
        return float(np.interp(x, np.log(self.mean_delay_ms), self.gamma_ms))

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> GammaCurve:
        pts = doc["points"]
        return cls(tuple(float(p["mean_delay_ms"]) for p in pts),
                   tuple(float(p["gamma_ms"]) for p in pts), str(doc.get("command", "")))


def load_gamma_curve() -> GammaCurve:
    """The measured curve shipped beside this module (``gamma_curve.json``)."""
    text = resources.files("aoi3d.policy").joinpath("gamma_curve.json").read_text()
    return GammaCurve.from_dict(json.loads(text))


class SlidingWindowUCB:
    """UCB over a fixed set of arms on the last ``window`` rewards only (Garivier & Moulines'
    SW-UCB): an arm with no reward in the window is tried first (in arm order); otherwise the
    arm maximising mean + ``explore`` · sqrt(ln(min(t, window)) / n), with its mean and count
    n over the window. Rewards are in the caller's units (``explore`` in the same)."""

    def __init__(self, n_arms: int, window: int = DEFAULT_WINDOW,
                 explore: float = DEFAULT_EXPLORE) -> None:
        if n_arms < 1 or window < 1 or not (math.isfinite(explore) and explore >= 0):
            raise ValueError(f"need n_arms >= 1, window >= 1, explore >= 0; got {n_arms}, "
                             f"{window}, {explore}")
        self.n_arms = n_arms
        self.window = window
        self.explore = float(explore)
        self._history: deque[tuple[int, float]] = deque(maxlen=window)
        self.t = 0

    def update(self, arm: int, reward: float) -> None:
        if not 0 <= arm < self.n_arms:
            raise ValueError(f"arm {arm} not in 0..{self.n_arms - 1}")
        if math.isfinite(reward):
            self._history.append((arm, float(reward)))
            self.t += 1

    def stats(self) -> tuple[np.ndarray, np.ndarray]:
        """(counts, means) of each arm over the window (mean NaN where count is 0)."""
        counts = np.zeros(self.n_arms)
        sums = np.zeros(self.n_arms)
        for a, r in self._history:
            counts[a] += 1
            sums[a] += r
        with np.errstate(invalid="ignore", divide="ignore"):
            means = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
        return counts, means

    def choose(self) -> int:
        counts, means = self.stats()
        untried = np.flatnonzero(counts == 0)
        if untried.size:
            return int(untried[0])
        horizon = max(2, min(self.t, self.window))
        ucb = means + self.explore * np.sqrt(math.log(horizon) / counts)
        return int(np.argmax(ucb))


# ---------------------------------------------------------------------------- policies
class _AdaptiveMat(BasePolicy):
    """MAT with a Γ the subclass moves; ``gamma_ms`` is the Γ in force."""

    kind = FAMILY
    family = FAMILY
    _gamma: float

    @property
    def gamma_ms(self) -> float:
        return self._gamma

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        return as_aoi_vector(aoi_ms) < self._gamma  # NaN compares False: never selected

    def __eq__(self, other: object) -> bool:  # two specs are equal policies (fresh state)
        return type(other) is type(self) and other.to_json() == self.to_json()  # type: ignore[attr-defined]

    def __hash__(self) -> int:
        return hash(self.spec)  # type: ignore[attr-defined]


class PluginPolicy(_AdaptiveMat):
    """Γ = Γ*(Ê[Y]): the measured best Γ at the estimated mean delay (see the module)."""

    def __init__(self, halflife_ms: float = DEFAULT_HALFLIFE_MS,
                 curve: GammaCurve | None = None) -> None:
        self.halflife_ms = number("halflife_ms", halflife_ms, minimum=1.0)
        self.curve = curve if curve is not None else load_gamma_curve()
        self.reset()

    def reset(self) -> None:
        self.estimator = DelayEstimator(self.halflife_ms)
        self._gamma = self.curve(math.nan)

    @property
    def spec(self) -> str:
        if self.halflife_ms == DEFAULT_HALFLIFE_MS:
            return "adaptive:plugin"
        return f"adaptive:plugin:{format_number(self.halflife_ms)}"

    @property
    def mean_delay_ms(self) -> float:
        """The estimated mean transmission time (NaN before any delivery)."""
        return self.estimator.mean_ms

    def observe(self, now_ms: float, deliveries: Iterable[Delivery]) -> None:
        for _cam, gen, delivered in deliveries:
            self.estimator.observe(gen, delivered)
        self._gamma = self.curve(self.estimator.mean_ms)

    def to_json(self) -> dict[str, Any]:
        h = self.halflife_ms
        return {"kind": FAMILY, "mode": "plugin",
                "halflife_ms": int(h) if float(h).is_integer() else h}

    def status(self) -> dict[str, Any]:
        """What a caller reports: Γ in force and the estimate it came from."""
        m = self.estimator.mean_ms
        return {"gamma_ms": self._gamma, "mean_delay_ms": None if math.isnan(m) else m,
                "samples": self.estimator.count}


class BanditPolicy(_AdaptiveMat):
    """A sliding-window UCB bandit over Γ arms, rewarded by the render's quality (see the
    module)."""

    wants_quality = True

    def __init__(self, window: int = DEFAULT_WINDOW,
                 arms_ms: Sequence[float] = DEFAULT_ARMS_MS,
                 explore: float = DEFAULT_EXPLORE, metric: str = "psnr_db") -> None:
        self.window = integer("window", window, minimum=1)
        arms = tuple(number("arm", a, minimum=0.0) for a in arms_ms)
        if not arms or len(set(arms)) != len(arms):
            raise PolicySpecError(f"arms must be distinct Γ values, got {list(arms_ms)}")
        self.arms_ms = tuple(sorted(arms))
        self.explore = number("explore", explore, minimum=0.0)
        if metric not in QUALITY_METRICS:
            raise PolicySpecError(f"metric must be one of {', '.join(QUALITY_METRICS)}, "
                                  f"got {metric!r}")
        self.metric = metric
        self.reset()

    def reset(self) -> None:
        self.ucb = SlidingWindowUCB(len(self.arms_ms), self.window, self.explore)
        self._arm = self.ucb.choose()
        self._gamma = self.arms_ms[self._arm]
        self._rewarded = True  # the first decision picks an arm
        self._now = -math.inf
        self._since: deque[tuple[float, int]] = deque(maxlen=4096)  # (from time s, arm)

    @property
    def spec(self) -> str:
        default = (self.arms_ms == DEFAULT_ARMS_MS and self.explore == DEFAULT_EXPLORE
                   and self.metric == "psnr_db")
        if default:
            return ("adaptive:bandit" if self.window == DEFAULT_WINDOW
                    else f"adaptive:bandit:{self.window}")
        arms = "/".join(format_number(a) for a in self.arms_ms)
        return (f"adaptive:bandit:{self.window}:{arms}:{format_number(self.explore)}"
                f":{self.metric}")

    def observe(self, now_ms: float, deliveries: Iterable[Delivery]) -> None:
        """Before each decision: choose a new arm when the last one has been rewarded."""
        self._now = float(now_ms)
        if self._rewarded:
            self._arm = self.ucb.choose()
            self._gamma = self.arms_ms[self._arm]
            self._rewarded = False
        if not self._since or self._since[-1][1] != self._arm:
            self._since.append((self._now, self._arm))

    def arm_at(self, time_ms: float) -> int | None:
        """The arm in force at the decision for ``time_ms`` (None: before the first)."""
        arm = None
        for start, a in self._since:
            if start > time_ms:
                break
            arm = a
        return arm

    def observe_quality(self, time_ms: float, scores: Mapping[str, float | None]) -> None:
        arm = self.arm_at(float(time_ms))
        value = scores.get(self.metric)
        if arm is None or value is None or not math.isfinite(value):
            return
        self.ucb.update(arm, float(value))
        if arm == self._arm:
            self._rewarded = True

    def to_json(self) -> dict[str, Any]:
        return {"kind": FAMILY, "mode": "bandit", "window": self.window,
                "arms_ms": [int(a) if a.is_integer() else a for a in self.arms_ms],
                "explore": self.explore, "metric": self.metric}

    def status(self) -> dict[str, Any]:
        counts, means = self.ucb.stats()
        return {"gamma_ms": self._gamma, "rewards": self.ucb.t,
                "arms": [{"gamma_ms": g, "n": int(n), "mean": None if math.isnan(m) else m}
                         for g, n, m in zip(self.arms_ms, counts, means, strict=True)]}


# ---------------------------------------------------------------------------- the kind
def _from_args(fields: list[str]) -> BasePolicy:
    if not fields:
        raise PolicySpecError("adaptive takes a mode: adaptive:plugin[:<halflife_ms>] or "
                              "adaptive:bandit[:<window>[:<arms a/b/c>[:<explore>[:<metric>]]]]")
    mode, *rest = fields
    if mode == "plugin":
        if len(rest) > 1:
            raise PolicySpecError("adaptive:plugin takes at most 1 parameter (halflife_ms)")
        if not rest:
            return PluginPolicy()
        return PluginPolicy(number("halflife_ms", rest[0], minimum=1.0))
    if mode == "bandit":
        if len(rest) > 4:
            raise PolicySpecError("adaptive:bandit takes at most 4 parameters "
                                  "(window, arms a/b/c, explore, metric)")
        kw: dict[str, Any] = {}
        if len(rest) > 0:
            kw["window"] = integer("window", rest[0], minimum=1)
        if len(rest) > 1:
            kw["arms_ms"] = [number("arm", a, minimum=0.0) for a in rest[1].split("/")]
        if len(rest) > 2:
            kw["explore"] = number("explore", rest[2], minimum=0.0)
        if len(rest) > 3:
            kw["metric"] = rest[3]
        return BanditPolicy(**kw)
    raise PolicySpecError(f"unknown adaptive mode {mode!r} (plugin, bandit)")


def _from_json(params: Mapping[str, Any]) -> BasePolicy:
    mode = params.get("mode")
    rest = {k: v for k, v in params.items() if k != "mode"}
    if mode == "plugin":
        extra = sorted(k for k in rest if k != "halflife_ms")
        if extra:
            raise PolicySpecError(f"adaptive plugin does not take key(s) {extra}")
        return PluginPolicy(rest.get("halflife_ms", DEFAULT_HALFLIFE_MS))
    if mode == "bandit":
        allowed = ("window", "arms_ms", "explore", "metric")
        extra = sorted(k for k in rest if k not in allowed)
        if extra:
            raise PolicySpecError(f"adaptive bandit does not take key(s) {extra}")
        arms = rest.get("arms_ms", DEFAULT_ARMS_MS)
        if not isinstance(arms, list | tuple):
            raise PolicySpecError(f"arms_ms must be a list of numbers, got {arms!r}")
        return BanditPolicy(rest.get("window", DEFAULT_WINDOW), arms,
                            rest.get("explore", DEFAULT_EXPLORE),
                            rest.get("metric", "psnr_db"))
    raise PolicySpecError(f'adaptive needs "mode": "plugin" or "bandit", got {mode!r}')


KIND = PolicyKind(FAMILY, "adaptive:<plugin|bandit>",
                  _from_args, _from_json, family=FAMILY)
"""The ``adaptive`` kind, registered by :mod:`aoi3d.policy`."""
