"""The quality metrics: one table, from which every list of their names is built.

Four **scores** judge a render against the truth (:mod:`aoi3d.quality`): PSNR, SSIM, LPIPS and
the reward (their weighted sum). Each is taken over the whole image at the decision's time;
PSNR and SSIM also over the *dynamic region* (the pixels that moved,
:func:`aoi3d.quality.dynamic_mask`); and each again against the truth at *display time* (the
decision's time plus its compute). Every such form is one :class:`Metric` of :data:`METRICS`:
its name (the field, column, JSON key and query parameter it is written under, everywhere the
same), its words, unit, better direction and the digits it is shown with.

A list of metric names anywhere (a CSV's columns, the metrics an optimum or an oracle may
take, a figure's panels) is built from these rows — by a selection named here (:data:`AT_DECISION`,
:data:`AT_DISPLAY`, :data:`LIVE`) or by picking the rows it needs in the order it writes them —
never spelled again, so a typo is an import error, not a new column. Standard library only.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from enum import StrEnum
from types import MappingProxyType

__all__ = [
    "AT_DECISION",
    "AT_DISPLAY",
    "BY_NAME",
    "LIVE",
    "LIVE_AT_DISPLAY",
    "LPIPS",
    "LPIPS_DISPLAY",
    "METRICS",
    "PSNR",
    "PSNR_DISPLAY",
    "PSNR_DYNAMIC",
    "PSNR_DYNAMIC_DISPLAY",
    "REWARD",
    "REWARD_DISPLAY",
    "REWARD_TERMS",
    "SCORES",
    "SSIM",
    "SSIM_DISPLAY",
    "SSIM_DYNAMIC",
    "Direction",
    "Metric",
    "find",
    "lower_is_better",
    "names_of",
]


class Direction(StrEnum):
    """Which way a metric is better."""

    HIGHER = "higher"
    LOWER = "lower"


@dataclass(frozen=True)
class Metric:
    """One metric: a score in one of its forms (whole image or dynamic region; at the
    decision's time or at display time)."""

    name: str
    """The field, column and key it is written under (``psnr_dynamic_db``)."""
    label: str
    """Its name in words (``dynamic-region PSNR``)."""
    unit: str
    """``"dB"``, or ``""`` for a number without a unit."""
    direction: Direction
    digits: int
    """Decimals it is shown with in tables and text."""
    score: str
    """The name of its score's whole-image, decision-time form (``psnr_db``)."""
    dynamic: bool = False
    """Taken over the dynamic region only."""
    display: bool = False
    """Taken against the truth at display time."""
    optional: bool = False
    """May be missing (None, a proto field not set): LPIPS without its weights, a
    dynamic-region score where nothing moved."""

    @property
    def higher_is_better(self) -> bool:
        return self.direction is Direction.HIGHER

    @property
    def sign(self) -> float:
        """+1 for a higher-is-better metric, −1 for a lower-is-better one."""
        return 1.0 if self.higher_is_better else -1.0

    @property
    def short(self) -> str:
        """The name without its unit (``psnr_db`` → ``psnr``): the key of the reward's weight
        (:class:`aoi3d.quality.RewardWeights`) and of the PPO env's and reports' columns."""
        return self.name.removesuffix(f"_{self.unit.lower()}") if self.unit else self.name

    @property
    def axis_label(self) -> str:
        """Its label on a figure's axis: ``PSNR (dB)``, ``LPIPS (lower is better)``."""
        unit = f" ({self.unit})" if self.unit else ""
        lower = " (lower is better)" if not self.higher_is_better else ""
        return f"{self.label}{unit}{lower}"

    def form(self, name: str, *, dynamic: bool = False, display: bool = False) -> Metric:
        """This score in another form, named ``name``; its words say which."""
        label = (("dynamic-region " if dynamic else "") + self.label
                 + (" at display time" if display else ""))
        return replace(self, name=name, label=label, dynamic=dynamic, display=display,
                       optional=self.optional or dynamic)


PSNR = Metric("psnr_db", "PSNR", "dB", Direction.HIGHER, 2, "psnr_db")
SSIM = Metric("ssim", "SSIM", "", Direction.HIGHER, 3, "ssim")
LPIPS = Metric("lpips", "LPIPS", "", Direction.LOWER, 3, "lpips", optional=True)
"""A learned distance: lower is better; None where its weights are not installed."""
REWARD = Metric("reward", "reward", "", Direction.HIGHER, 3, "reward")
"""The weighted sum of the others (:class:`aoi3d.quality.RewardWeights`)."""
PSNR_DYNAMIC = PSNR.form("psnr_dynamic_db", dynamic=True)
SSIM_DYNAMIC = SSIM.form("ssim_dynamic", dynamic=True)
PSNR_DISPLAY = PSNR.form("psnr_display_db", display=True)
SSIM_DISPLAY = SSIM.form("ssim_display", display=True)
LPIPS_DISPLAY = LPIPS.form("lpips_display", display=True)
REWARD_DISPLAY = REWARD.form("reward_display", display=True)
PSNR_DYNAMIC_DISPLAY = PSNR.form("psnr_dynamic_display_db", dynamic=True, display=True)

SCORES = (PSNR, SSIM, LPIPS, REWARD)
"""The four scores, whole image at the decision's time, in the order lists give them."""
METRICS = (PSNR, SSIM, LPIPS, REWARD, PSNR_DYNAMIC, SSIM_DYNAMIC,
           PSNR_DISPLAY, SSIM_DISPLAY, LPIPS_DISPLAY, REWARD_DISPLAY, PSNR_DYNAMIC_DISPLAY)
"""Every metric: the scores, then their dynamic-region forms, then both at display time."""

BY_NAME: Mapping[str, Metric] = MappingProxyType({m.name: m for m in METRICS})
"""Every metric by its name."""


def names_of(metrics: Iterable[Metric]) -> tuple[str, ...]:
    """The names of ``metrics``, in their order."""
    return tuple(m.name for m in metrics)


AT_DECISION = names_of(m for m in METRICS if not m.display)
"""``psnr_db, ssim, lpips, reward, psnr_dynamic_db, ssim_dynamic``: what an episode scores at
the decision's time; what an optimum, an oracle or a replay's comparison may take."""
AT_DISPLAY = names_of(m for m in METRICS if m.display)
"""``psnr_display_db, ssim_display, lpips_display, reward_display, psnr_dynamic_display_db``."""
LIVE = names_of((PSNR, PSNR_DYNAMIC, SSIM, LPIPS, REWARD))
"""What a live run shows and summarises per render (the console's charts, ``aoi3d live
sweep``), in that order."""
LIVE_AT_DISPLAY = names_of((PSNR_DISPLAY, PSNR_DYNAMIC_DISPLAY))
"""What a live run also summarises against the truth at display time (when the render was
ready: what a viewer saw), beside :data:`LIVE` (the console draws the first beside PSNR)."""
REWARD_TERMS = tuple(m.short for m in METRICS if not m.display and m.score != REWARD.name)
"""``psnr, ssim, lpips, psnr_dynamic, ssim_dynamic``: what the reward may weigh (the fields of
:class:`aoi3d.quality.RewardWeights`, in their order)."""


def find(name: str) -> Metric | None:
    """The metric written under ``name`` (or its :attr:`Metric.short` name); None for a
    name that is not a metric's (``n_selected``)."""
    found = BY_NAME.get(name)
    if found is None:
        found = next((m for m in METRICS if m.short == name), None)
    return found


def lower_is_better(name: str) -> bool:
    """Whether the metric named ``name`` is better lower; False for a name that is not a
    metric's."""
    found = find(name)
    return found is not None and not found.higher_is_better
