"""Live against virtual: does the virtual clock's twin of the pool put the same Γ first as the
live pipeline, at display time?

Called from ``bench/science.py`` (``make science``) and alone with ``python -m bench.science
--only twin``, which merges into the existing ``claims.json`` / ``docs/science.md``. For each
time scale of :data:`TIME_SCALES` it runs ``aoi3d live sweep --up`` — a real pipeline with
its defaults (the stream carry at 25 steps, two workers), the policies of :data:`POLICIES`
in turn, interleaved over the repeats, the model reset at each change — and, on the same
seed block, the virtual clock through the pool's twin (``--sim-pool``: the pipeline's
workers and time scale, each job charged the median the live workers timed for its step
count and frames). The live network's seed is the block's first seed (``AOI3D_NETWORK_SEED``); the
twin's episodes are the block's seeds.

Per time scale: PSNR at display time, live (mean ± 95 % CI over the window's renders) and on
the twin (over seeds), their difference, the share of decisions rendered and the display lag
on each side; whether the twin's best Γ is the live one, and the mean absolute difference
(the goal: the same best Γ, |Δ| ≤ 0.5 dB). Reported either way: an open question, not a
claim of docs/research.md.
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench.ports import BENCH_BLOCKS

TIME_SCALES = (0.3, 1.0)
POLICIES = ("mat:40", "mat:70", "mat:100", "mat:160", "all")
GOAL_DB = 0.5
"""The largest mean |live − twin| the twin is meant to keep (issue 49)."""
PORTS = BENCH_BLOCKS["science_twin"]


def _folder(scale: float) -> str:
    return f"ts{scale:g}".replace(".", "_")


FRESH_FRACTION = "1"
"""AOI3D_DISPATCHER_FRESH_FRACTION of the live runs (and so of their twin)."""


def run_all(exe: str, out: Path, runner: Callable[[list[str], list[dict[str, Any]]], float],
            log: list[dict[str, Any]], *, seeds: int, seed_offset: int, cache: Path,
            settle_s: float = 10.0, measure_s: float = 40.0, repeats: int = 2,
            workers: int = 2, reuse: bool = False, extra: tuple[str, ...] = ()) -> None:
    """One live sweep with its twin per time scale, into ``out/twin/<ts>`` (``reuse``: one
    whose results.json exists is kept)."""
    os.environ["AOI3D_NETWORK_SEED"] = str(seed_offset)  # the live run's seed (inherited)
    # the dispatcher these results were measured with (no wait for a fresher decision; the
    # default is 0.5 since): the twin reads it from the live status, so both run it
    os.environ["AOI3D_DISPATCHER_FRESH_FRACTION"] = FRESH_FRACTION
    for scale in TIME_SCALES:
        dest = out / "twin" / _folder(scale)
        if reuse and (dest / "results.json").exists():
            continue
        runner([exe, "live", "sweep", "--up", "--time-scale", f"{scale:g}",
                "--workers", str(workers), "--policies", ",".join(POLICIES),
                "--settle-s", f"{settle_s:g}", "--measure-s", f"{measure_s:g}",
                "--repeats", str(repeats), "--sim-pool", "--sim-seeds", str(seeds),
                "--sim-seed-offset", str(seed_offset), "--cache", str(cache),
                "--port-offset", str(PORTS.offset), "--zenoh-port", str(PORTS.zenoh),
                *extra, "--out", str(dest)], log)


def _live_side(doc: dict[str, Any], policy: str) -> dict[str, Any]:
    """The live windows of ``policy``: the share of their decisions rendered and the median
    display lag of their renders (scene ms)."""
    ms = [m for m in doc["measurements"] if m["policy"] == policy]
    made = sum(m["last_decision"] - m["first_decision"] + 1 for m in ms)
    scored = sum(len(m["qualities"]) for m in ms)
    lags = [q["display_time_ms"] - q["time_ms"] for m in ms for q in m["qualities"]
            if q.get("display_time_ms") is not None]
    return {"rendered_fraction": scored / made if made > 0 else None,
            "display_lag_ms": statistics.median(lags) if lags else None}


def verdicts(out: Path) -> dict[str, Any]:
    """Per time scale, the table and the verdict, as claims.json keeps them (``live_twin``)."""
    section: dict[str, Any] = {"policies": list(POLICIES), "goal_db": GOAL_DB, "scales": {}}
    for scale in TIME_SCALES:
        path = out / "twin" / _folder(scale) / "results.json"
        if not path.exists():
            continue
        doc = json.loads(path.read_text())
        sim = doc.get("sim") or {}
        rows = []
        for r in doc["results"]:
            twin = sim.get(r["policy"], {})
            rows.append({
                "policy": r["policy"], "live": r["psnr_display_db"], "live_n": r["n"],
                "twin": twin.get("psnr_display_db"),
                "diff_db": r.get("live_minus_sim_display_db"),
                "live_side": _live_side(doc, r["policy"]),
                "twin_rendered_fraction": (twin.get("rendered_fraction") or {}).get("mean"),
                "twin_display_lag_ms": (twin.get("display_lag_ms") or {}).get("mean")})
        section["scales"][f"{scale:g}"] = _verdict(rows, sim.get("_config") or {}, doc)
    return section


def _verdict(rows: list[dict[str, Any]], cfg: dict[str, Any], doc: dict[str, Any]
             ) -> dict[str, Any]:
    def best(side: str) -> str | None:
        have = [r for r in rows if r[side] is not None and r[side].get("mean") is not None]
        return max(have, key=lambda r: r[side]["mean"])["policy"] if have else None

    diffs = [abs(r["diff_db"]) for r in rows if r["diff_db"] is not None]
    mean_abs = sum(diffs) / len(diffs) if diffs else None
    live_best, twin_best = best("live"), best("twin")
    same = live_best is not None and live_best == twin_best
    return {
        "rows": rows, "live_best": live_best, "twin_best": twin_best, "same_best": same,
        "mean_abs_diff_db": mean_abs,
        "holds": bool(same and mean_abs is not None and mean_abs <= GOAL_DB),
        "twin": {k: cfg.get(k) for k in ("pool_workers", "time_scale", "job_ms",
                                         "compute_fixed_ms", "compute_step_ms")},
        "twin_seeds": next((r["twin"]["n"] for r in rows if r["twin"]), None),
        "settings": {k: doc["settings"].get(k) for k in ("settle_s", "measure_s", "repeats")},
        "wall_s": doc.get("wall_s")}


def _jobs_text(table: list[list[float]]) -> str:
    """The timed jobs, per step count: the range of medians over the frames timed."""
    def span(values: list[float], fmt: str) -> str:
        lo, hi = format(min(values), fmt), format(max(values), fmt)
        return lo if lo == hi else f"{lo}–{hi}"

    out = []
    for steps in sorted({int(e[0]) for e in table} - {0}):  # (0 steps: an empty selection)
        ms = [float(e[-1]) for e in table if int(e[0]) == steps]
        frames = [float(e[1]) for e in table if int(e[0]) == steps and len(e) == 3]
        out.append(f"{steps} steps {span(ms, '.0f')} ms"
                   + (f" ({span(frames, '.0f')} frames)" if frames else ""))
    return ", ".join(out)


def _cell(stat: dict[str, Any] | None) -> str:
    if not stat or stat.get("mean") is None:
        return "—"
    return f"{stat['mean']:.2f} ± {stat['ci95']:.2f}"


def _num(v: float | None, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def render_lines(section: dict[str, Any], rel: str) -> list[str]:
    """docs/science.md's section."""
    lines = ["## Live against the virtual clock's twin of the pool", "",
             "The pipeline's defaults (the stream carry at 25 steps, two workers, exp:60), "
             "each Γ live (`aoi3d live sweep --up`) and on the virtual clock through the twin "
             "of the pool (the same dispatcher code; the pipeline's workers and time scale; "
             "each job charged the median the live workers timed for its step count and "
             "frames). PSNR "
             "at display time, dB; live over the renders of the windows, the twin over "
             "seeds (95 % CIs). An open question, reported either way: does the twin put the "
             f"same Γ first, within {section['goal_db']:g} dB on average?", ""]
    for scale, v in section["scales"].items():
        twin = v["twin"]
        jobs = _jobs_text(twin.get("job_ms") or [])
        lines += [f"### Time scale {scale}", "",
                  f"Twin: {twin.get('pool_workers')} workers, jobs of {jobs or '—'} (wall, "
                  f"median as timed live), {v['twin_seeds']} seeds; live: "
                  f"{v['settings']['measure_s']:g} s × {v['settings']['repeats']} per policy.",
                  "", "| policy | live | twin | live − twin | rendered live / twin | "
                      "display lag live / twin (ms) |", "|---|---|---|---|---|---|"]
        for r in v["rows"]:
            ls = r["live_side"]
            lines.append(
                f"| {r['policy']} | {_cell(r['live'])} (n {r['live_n']}) | {_cell(r['twin'])} "
                f"| {_num(r['diff_db'], '+.2f')} | {_num(ls['rendered_fraction'], '.0%')} / "
                f"{_num(r['twin_rendered_fraction'], '.0%')} | "
                f"{_num(ls['display_lag_ms'], '.0f')} / {_num(r['twin_display_lag_ms'], '.0f')} |")
        lines += ["", f"Best live: `{v['live_best']}`; best on the twin: `{v['twin_best']}` "
                      f"({'the same' if v['same_best'] else 'not the same'}); mean |live − "
                      f"twin| {_num(v['mean_abs_diff_db'], '.2f')} dB: "
                      f"**{'yes' if v['holds'] else 'no'}**.", ""]
    lines += [f"Outputs: `{rel}/twin/<time scale>/` (each sweep's results.json, CSV, PNG).", ""]
    return lines
