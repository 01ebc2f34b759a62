"""What a live sweep measured, summarised: the windows of :class:`Measurement`, the per-policy
statistics of :func:`summarise`, the virtual clock's numbers set beside them
(:func:`with_sim`), and the rows and entries the sweep writes (``points.csv``,
``renders.csv``, the windows of ``results.json``).

Pure: the windows come from whoever talked to the pipeline (``aoi3d live sweep``); the dispatcher
status dicts are its ``GET /status`` answers as they are.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from aoi3d.metric import LIVE, LIVE_AT_DISPLAY
from aoi3d.stats import mean_ci95

__all__ = ["DISPLAY_METRICS", "METRICS", "Measurement", "measurement_doc", "points_rows",
           "render_latency_s", "render_rows", "steps_per_decision", "summarise", "with_sim"]

DISPLAY_METRICS = LIVE_AT_DISPLAY
"""Scores against the truth at display time — when the render was ready, what a viewer saw
(the metrics service's ``*_display`` fields; the virtual clock's, at its cost model) — beside
the scores at the decision's time: :data:`aoi3d.metric.LIVE_AT_DISPLAY`."""
METRICS = (*LIVE, *DISPLAY_METRICS)
"""Per-render quality fields summarised per policy (absent ones are reported as null):
:data:`aoi3d.metric.LIVE`, then the display-time ones."""


@dataclass
class Measurement:
    """One policy's window: its Quality entries and the decisions sampled during it."""

    policy: str
    repeat: int
    first_decision: int
    last_decision: int
    wall_s: float
    qualities: list[dict[str, Any]]
    decisions: list[dict[str, Any]]
    render_png: bytes = b""
    render_decision: int | None = None


def summarise(measurements: Sequence[Measurement], order: Sequence[str]) -> list[dict[str, Any]]:
    """One result per policy (in ``order``): per-render quality statistics and the cameras
    the window's decisions used."""
    out = []
    for spec in order:
        ms = [m for m in measurements if m.policy == spec]
        qs = [q for m in ms for q in m.qualities]
        ds = [d for m in ms for d in m.decisions]
        used = [len(d["selected"]) for d in ds]
        aoi = [float(sum(r["aoi_ms"] for r in d["selected"]) / len(d["selected"]))
               for d in ds if d["selected"]]
        row: dict[str, Any] = {"policy": spec, "n": len(qs)}
        for metric in METRICS:
            row[metric] = mean_ci95([q.get(metric) for q in qs]).to_dict()
        row["cameras_used"] = mean_ci95(used).to_dict()
        row["aoi_used_ms"] = mean_ci95(aoi).to_dict()
        row["render_views"] = mean_ci95([q.get("n_views") for q in qs]).to_dict()
        out.append(row)
    return out


def with_sim(results: Sequence[dict[str, Any]], sim: Mapping[str, Any]) -> None:
    """Set the virtual clock's PSNR beside each live result (``sim_psnr_db``) and the
    difference of the means (``live_minus_sim_db``; None where either is missing); likewise
    at display time (``sim_psnr_display_db``, ``live_minus_sim_display_db``; None where the
    virtual clock has no display score)."""
    for r in results:
        for metric, diff in (("psnr_db", "live_minus_sim_db"),
                             ("psnr_display_db", "live_minus_sim_display_db")):
            stat = sim[r["policy"]].get(metric)
            s = None if stat is None else stat["mean"]
            live = r[metric]["mean"]
            r[f"sim_{metric}"] = stat
            r[diff] = None if s is None or live is None else live - s


def render_latency_s(status: Mapping[str, Any]) -> float:
    """Wall seconds a render may take, from the dispatcher's status: its own training at the
    measured step rate, plus scoring; at least 2 s."""
    rate = status.get("steps_per_s") or 0.0
    steps = status.get("render_steps") or 0
    return max(2.0, 1.5 * steps / rate + 1.0 if rate > 0 else 2.0 + steps / 10.0)


def steps_per_decision(s0: Mapping[str, Any], s1: Mapping[str, Any],
                       measurements: Sequence[Measurement]) -> int:
    """Background training steps per decision over the sweep (warm/fork carry), from the
    dispatcher's status before (``s0``) and after (``s1``)."""
    decisions = sum(m.last_decision - m.first_decision + 1 for m in measurements)
    renders = sum(len(m.qualities) for m in measurements)
    steps = s1.get("steps_total", 0) - s0.get("steps_total", 0)
    steps -= renders * int(s1.get("render_steps") or 0)
    return max(1, round(steps / decisions)) if decisions > 0 and steps > 0 else 1


def measurement_doc(m: Measurement) -> dict[str, Any]:
    """A window for results.json: its renders' Quality, and of the decisions sampled in it
    only what the summary uses (cameras used, mean AoI of the used frames)."""
    doc = {k: v for k, v in vars(m).items() if k not in ("render_png", "decisions")}
    doc["decisions_sampled"] = [
        {"decision_id": d["decision_id"], "cameras_used": len(d["selected"]),
         "aoi_used_ms": (sum(r["aoi_ms"] for r in d["selected"]) / len(d["selected"])
                         if d["selected"] else None)}
        for d in m.decisions]
    return doc


def points_rows(results: Sequence[dict[str, Any]], sim: Mapping[str, Any] | None
                ) -> list[dict[str, Any]]:
    """``points.csv``: per policy, each metric's mean and 95% CI, and the virtual clock's
    mean where there is one (the display-time scores last: the columns before them are the
    ones the file always had)."""
    decision_time = [m for m in METRICS if m not in DISPLAY_METRICS]
    rows = []
    for r in results:
        row: dict[str, Any] = {"policy": r["policy"], "n": r["n"]}
        for metric in (*decision_time, "cameras_used", "aoi_used_ms", *DISPLAY_METRICS):
            row[metric] = r[metric]["mean"]
            row[f"{metric}_ci95"] = r[metric]["ci95"]
            if sim is not None and metric in sim.get(r["policy"], {}):
                row[f"sim_{metric}"] = sim[r["policy"]][metric]["mean"]
        rows.append(row)
    return rows


def render_rows(measurements: Sequence[Measurement]) -> list[dict[str, Any]]:
    """``renders.csv``: one row per scored render, its policy and repeat first (list fields
    left out)."""
    return [{"policy": m.policy, "repeat": m.repeat,
             **{k: v for k, v in q.items() if not isinstance(v, list)}}
            for m in measurements for q in m.qualities]
