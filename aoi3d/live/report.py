"""The results of a live sweep as one typed value (:class:`LiveSweep`): the per-policy
summaries, the interior-maximum verdict per metric, the settings, the virtual clock's numbers
and the windows; and the files it writes (``results.json``, ``points.csv``, ``renders.csv``)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aoi3d.experiment.optimum import unpaired_interior_maximum
from aoi3d.experiment.report import code_version, machine, write_csv, write_json
from aoi3d.live.summary import (
    METRICS,
    Measurement,
    measurement_doc,
    points_rows,
    render_rows,
    summarise,
    with_sim,
)

__all__ = ["LiveSweep", "Verdict"]


@dataclass(frozen=True)
class Verdict:
    """Whether a metric's best policy is an interior maximum beyond its 95% CI
    (:func:`aoi3d.experiment.optimum.unpaired_interior_maximum`)."""

    metric: str
    best: str
    best_mean: float
    interior: bool
    beyond_ci: bool

    @property
    def text(self) -> str:
        return ("an interior maximum beyond its 95% CI (Welch, unpaired)" if self.beyond_ci
                else "interior, but within the CIs of an end" if self.interior
                else "not interior")


@dataclass
class LiveSweep:
    """What ``aoi3d live sweep`` found: :meth:`of` builds it from the measured windows."""

    results: list[dict[str, Any]]
    """Per policy, :func:`~aoi3d.live.summary.summarise`'s row (with the virtual clock's PSNR
    beside it when there is one)."""
    shape: dict[str, dict[str, Any] | None]
    """Per metric of :data:`~aoi3d.live.summary.METRICS`, the unpaired interior-maximum test."""
    settings: dict[str, Any]
    sim: dict[str, Any] | None
    measurements: list[Measurement]

    @classmethod
    def of(cls, measurements: Sequence[Measurement], order: Sequence[str], *,
           settings: dict[str, Any], sim: dict[str, Any] | None) -> LiveSweep:
        results = summarise(measurements, order)
        if sim is not None:
            with_sim(results, sim)
        shape = {m: unpaired_interior_maximum(results, m) for m in METRICS}
        return cls(results, shape, settings, sim, list(measurements))

    def verdicts(self) -> list[Verdict]:
        """The metrics the test could judge, in :data:`METRICS` order."""
        return [Verdict(metric, info["best"], info["best_mean"], info["interior"],
                        info["beyond_ci"])
                for metric, info in self.shape.items() if info is not None]

    def document(self, wall_s: dict[str, float]) -> dict[str, Any]:
        """``results.json``: the results, the test, the settings, the virtual clock, the wall
        time, the windows, and ``meta`` (the code version, the machine, the time)."""
        return {
            "results": self.results,
            "unpaired_interior_maximum": self.shape,
            "settings": self.settings,
            "sim": self.sim,
            "wall_s": wall_s,
            "measurements": [measurement_doc(m) for m in self.measurements],
            "meta": {"code_version": code_version(), "machine": machine(),
                     "finished_unix_s": time.time()},
        }

    def write(self, out: Path, doc: dict[str, Any]) -> None:
        """``results.json`` (``doc``, :meth:`document`), ``points.csv`` and ``renders.csv``
        in ``out`` (made if missing)."""
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "results.json", doc)
        write_csv(out / "points.csv", points_rows(self.results, self.sim))
        write_csv(out / "renders.csv", render_rows(self.measurements))
