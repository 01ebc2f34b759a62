"""`make docs`: the measurement pages of docs/, generated from ``results/``.

Every number on docs/measurements.md is read here from a file under ``results/`` (the
JSON, CSV or text a bench wrote), printed beside the command that redoes it and the file it
came from. Nobody edits the page by hand: a bench writes its result file, ``make docs``
rewrites the page, and ``tests/unit/rules/test_measurements_doc.py`` regenerates it into a
temporary folder and fails when the committed page differs (a hand edit, or a result file
committed without its page). The prose that interprets the numbers lives in the hand-written
pages (docs/operations.md, docs/performance.md, ...), which link here instead of copying
them.

Why in bench/: the generator reads what the benches write and nothing else; it is neither
domain code (aoi3d/, which imports nothing of bench/) nor a service. It uses only the
standard library, so it runs without the project installed.

    python -m bench.docs            # rewrite docs/measurements.md
    python -m bench.docs --check    # exit 1 (and say which page) when a page is stale
    python -m bench.docs --out DIR  # write the pages under DIR instead of docs/

A result file no section renders must be listed in ``ELSEWHERE`` with the page that
discusses it; the test fails on a file that is neither, so a new result cannot be lost.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aoi3d.metric import BY_NAME

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "results"
PAGE = "measurements.md"

#: Result files (paths relative to results/) that no section below renders, with the
#: page that reports them.
ELSEWHERE: dict[str, str] = {
    "adaptive": "[experiments.md](experiments.md), \"Does an adaptive Γ beat the best fixed "
                "rule on a changing channel?\" (`python bench/adaptive.py`)",
    "adaptive-spread2000": "[experiments.md](experiments.md), \"Does an adaptive Γ beat the "
                           "best fixed rule on a changing channel?\" (cameras 2 s apart)",
    "adaptive-gamma-curve": "[experiments.md](experiments.md), the plug-in's Γ*(E[Y]) curve "
                            "(`bench/adaptive_curve.sh`, `bench/adaptive_curve.py`)",
    "adaptive-halflife": "[experiments.md](experiments.md), the plug-in's half-life "
                         "(`python bench/adaptive_halflife.py`)",
    "switching": "[experiments.md](experiments.md), \"How much could a Γ that follows a "
                 "changing channel gain?\" (`python bench/switching.py`)",
    "live-channel": "[channels.md](channels.md), the console on a changing channel "
                    "(`python bench/live_channel.py`)",
    "science": "[science.md](science.md) (written by `make science`, `bench/science.py`)",
    "timefield": "[experiments.md](experiments.md), \"Does a time-aware field move the "
                 "tradeoff?\" (`bench/recon.py --field flow`, `bench/scale.py --configs "
                 "…:flow`)",
    "streaming": "[performance.md](performance.md), \"Streaming reconstruction\", and "
                 "[experiments.md](experiments.md), \"Does the tradeoff survive at display "
                 "time?\" (`bench/recon.py --carry warm`, `bench/scale.py`, "
                 "`bench/display_sweep.py`)",
    "realtime/before-after": "[performance.md](performance.md), \"Real time on two cores\" "
                             "(bench/realtime.py before and after, paired)",
    "live-default": "[performance.md](performance.md), \"The live default\" "
                    "(`python -m bench.live_default`)",
    "ppo_arch.json": "[ppo.md](ppo.md), \"Which network\" (`python bench/ppo_arch.py`)",
    "ppo_budget.json": "[ppo.md](ppo.md), the budget trade (`python bench/ppo_budget.py`)",
    "ppo-dynamic": "[ppo.md](ppo.md), the dynamic-region reward",
    "ppo-state-300": "[ppo.md](ppo.md), \"A richer state\"",
    "state-features.json": "[ppo.md](ppo.md), \"A richer state\" "
                           "(`python bench/state_features.py`)",
    "state-features.txt": "[ppo.md](ppo.md), \"A richer state\" "
                          "(`python bench/state_features.py`)",
    "oracle-300": "[experiments.md](experiments.md), \"How much can a frame-selection policy "
                  "gain over the best fixed rule?\"",
    "oracle-greedy-300": "[experiments.md](experiments.md), \"The greedy search\"",
    "online-live/learners.csv": "[ppo.md](ppo.md), online learning live (its figure)",
    "online-live/qualities.csv": "[ppo.md](ppo.md), online learning live (its figure)",
    "online-live/online_live.png": "[ppo.md](ppo.md), online learning live",
    "live-sweep/renders.csv": "the per-render rows behind \"The tradeoff, live\"",
    "live-sweep/points.csv": "the table of \"The tradeoff, live\" as CSV",
    "live-sweep/live_sweep.png": "figures/live_sweep.png",
    "live-sweep/live_views.png": "figures/live_views.png",
    "live-sweep-192x144/renders.csv": "the per-render rows behind \"At 192×144 pixels\"",
    "live-sweep-192x144/points.csv": "the table of \"At 192×144 pixels\" as CSV",
    "live-sweep-192x144/live_sweep.png": "figures/live_sweep_192x144.png",
    "live-sweep-192x144/live_views.png": "figures/live_views_192x144.png",
}


# -- formatting -------------------------------------------------------------------------------

def f(x: Any, digits: int = 2) -> str:
    """A number with ``digits`` decimals; — for a missing one (never 0)."""
    if x is None:
        return "—"
    return f"{float(x):.{digits}f}"


def ci(stat: dict[str, Any] | None, digits: int = 2) -> str:
    """``mean ± ci95`` of a ``{"mean", "ci95", "n"}`` record."""
    if not stat or stat.get("mean") is None:
        return "—"
    if stat.get("ci95") is None:
        return f(stat["mean"], digits)
    return f"{f(stat['mean'], digits)} ± {f(stat['ci95'], digits)}"


def diff(d: dict[str, Any], digits: int = 2) -> str:
    """A ``{"difference", "ci95"}`` record, signed."""
    return f"{float(d['difference']):+.{digits}f} ± {float(d['ci95']):.{digits}f}"


def table(header: list[str], rows: list[list[Any]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return out


#: The live sweeps' carry (``make bench-live``, ``make bench-192``): not the live default.
FRESH100 = ("export AOI3D_DISPATCHER_CARRY=fresh AOI3D_DISPATCHER_RENDER_STEPS=100   # the carry "
            "these were measured with (the live default: stream, 25)")


def today(command: str) -> str:
    """A command a result file recorded, with its output where the file now lies: the results
    moved from bench/results/ to results/, and the files keep the command as it was run."""
    return command.replace("--out bench/results/", "--out results/")


def redo(*commands: str) -> list[str]:
    return ["```bash", *(today(c) for c in commands), "```"]


def source(*paths: str) -> str:
    return "Source: " + ", ".join(f"`results/{p}`" for p in paths) + "."


def load(results: Path, name: str) -> dict[str, Any]:
    return json.loads((results / name).read_text())


def load_lines(results: Path, name: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (results / name).read_text().splitlines()
            if line.strip()]


# -- sections ---------------------------------------------------------------------------------

def live_sweep(results: Path) -> tuple[list[str], set[str]]:
    r = load(results, "live-sweep/results.json")
    sim16 = load(results, "live-sweep/sim-16-seeds.json")
    s, meta = r["settings"], r["meta"]
    first = r["results"][0]["policy"]
    rows = []
    for p in r["results"]:
        v = sim16.get(p["policy"], {}).get("psnr_db")
        v4 = (r.get("sim") or {}).get(p["policy"], {}).get("psnr_db")
        gap = p["psnr_db"]["mean"] - v["mean"] if v else None
        rows.append([f"`{p['policy']}`", p["n"], ci(p["psnr_db"]), ci(p["psnr_dynamic_db"]),
                     f(p["ssim"]["mean"], 3), f(p["lpips"]["mean"], 3),
                     f(p["cameras_used"]["mean"], 1), ci(v4), ci(v),
                     ci(sim16.get(p["policy"], {}).get("psnr_dynamic_db")),
                     "—" if gap is None else f"{gap:+.2f}"])
    lines = [
        "## The tradeoff, live",
        "",
        "Each policy set on the running pipeline (`PUT /policy`), left to settle, then the "
        "Quality of every render of the decisions of the next window; policies interleaved "
        "over the repeats. Criterion for an interior maximum (`unpaired_interior_maximum`): "
        "the best policy is neither end and the 95 % interval of its difference to each end "
        "(Welch, renders as samples) lies above zero.",
        "",
        *redo("make bench-live   # = the commands below",
              FRESH100,
              "aoi3d live sweep --up --port-offset 2000 --zenoh-port 9447 "
              "--policies mat:40,mat:70,mat:130,all \\",
              "    --settle-s 10 --measure-s 75 --repeats 3 --sim-seeds 16 "
              "--out results/live-sweep"),
        "",
        f"Settings: time scale 0.1, delay `{s['channel']['delay']}`, carry `{s['carry']}`, "
        f"{s['render_steps']} steps per render, {s['measure_s']:.0f} s windows × "
        f"{s['repeats']} repeats, {s['trainer_steps_per_s']:.0f} training steps/s; "
        f"{r['wall_s']['total'] / 60:.1f} min in all; code {meta['code_version']}, "
        f"{meta['machine']['cpu_count']} cores, load {meta['machine']['loadavg'][0]} at the end. "
        f"The virtual clock ran in the same command on {r['sim'][first]['psnr_db']['n']} "
        f"seeds; the same code ran afterwards on {sim16[first]['psnr_db']['n']} "
        f"seeds ({sim16['wall_s'] / 60:.1f} min; `make bench-live` now does both at once).",
        "",
        *table(["policy", "renders", "PSNR (dB)", "dynamic-region PSNR (dB)", "SSIM", "LPIPS",
                "cameras", f"virtual clock PSNR, {r['sim'][first]['psnr_db']['n']} seeds",
                f"virtual clock PSNR, {sim16[first]['psnr_db']['n']} seeds",
                f"virtual clock dynamic-region PSNR, {sim16[first]['psnr_db']['n']} seeds",
                "live − virtual PSNR (dB)"], rows),
        "",
    ]
    lines += interior_lines(r["interior_maximum"])
    lines.append("")
    return lines, {"live-sweep/results.json", "live-sweep/sim-16-seeds.json"}


def interior_lines(im: dict[str, Any]) -> list[str]:
    out = []
    for metric, m in im.items():
        verdict = ("interior maximum beyond its interval" if m["interior"] and m["beyond_ci"]
                   else "interior, within its interval" if m["interior"] else "not interior")
        known = BY_NAME.get(metric)
        ends = "; ".join(f"best − `{end}` {diff(d, known.digits if known else 2)}"
                         for end, d in m["best_minus_end"].items())
        out.append(f"- {known.label if known else metric}: best `{m['best']}`, {verdict} "
                   f"({ends}).")
    return out


def live_192(results: Path) -> tuple[list[str], set[str]]:
    r = load(results, "live-sweep-192x144/results.json")
    sc = load(results, "scale-192x144.json")
    rows = [[f"`{p['policy']}`", p["n"], ci(p["psnr_db"]), ci(p["psnr_dynamic_db"]),
             f(p["ssim"]["mean"], 3), f(p["lpips"]["mean"], 3), f(p["reward"]["mean"], 3),
             f(p["cameras_used"]["mean"], 1)] for p in r["results"]]
    lines = [
        "## At 192×144 pixels",
        "",
        *redo("make bench-192    # = the scene and the commands below",
              FRESH100,
              "aoi3d scene generate --width 192 --height 144 --processes 2 "
              "--out data/turbine-rotor-192x144",
              "aoi3d live sweep --up --workers 2 --dataset data/turbine-rotor-192x144 "
              "--port-offset 2000 \\",
              "    --zenoh-port 9447 --policies mat:40,mat:70,mat:130,all --settle-s 10 "
              "--measure-s 75 \\",
              "    --repeats 2 --no-sim --out results/live-sweep-192x144",
              sc["command"]),
        "",
        f"Live sweep: 2 workers, time scale 0.1, {r['wall_s']['live'] / 60:.1f} min; code "
        f"{r['meta']['code_version']}, {r['meta']['machine']['cpu_count']} cores.",
        "",
        *table(["policy", "renders", "PSNR (dB)", "dynamic-region PSNR (dB)", "SSIM", "LPIPS",
                "reward", "cameras"], rows),
        "",
        *interior_lines(r["unpaired_interior_maximum"]),
        "",
        "The pool at 192×144 (`mat:70`):",
        "",
        *scale_table([("192×144", row) for row in sc["rows"]]),
        "",
    ]
    return lines, {"live-sweep-192x144/results.json", "scale-192x144.json"}


def _busy(row: dict[str, Any]) -> str:
    return ", ".join(f"{v:.2f}" for v in row["busy_fraction"].values())


def _cores(by_process: dict[str, float], name: str) -> float:
    """A process's cores; the dispatcher's were stored as ``trainer`` before its rename."""
    if name == "dispatcher" and name not in by_process:
        name = "trainer"
    return by_process.get(name, 0)


def scale_table(rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    out = []
    for label, row in rows:
        out.append([label, f"{row['workers']} × {row['sites']}",
                     f(row["renders_per_s"]), f"{row['fraction_rendered'] * 100:.0f} %",
                     f"{row['wait_s_mean']:.2f} s", f"{row['render_age_s_mean']:.2f} s",
                     f"{ci(row['psnr_db'])} ({row['psnr_db']['n']})",
                     f"{row['zenoh_bytes_per_s'] / 1e6:.2f}", _busy(row)])
    return table(["run", "workers × sites", "renders/s", "decisions rendered",
                  "decision → worker", "render age", "PSNR, dB (renders)",
                  "router MB/s", "workers busy"], out)


SCALE_RUNS = (  # newest first
    ("scale-fused.json", "fused training step"),
    ("scale.json", "two passes"),
    ("scale-repeat.json", "the first run's repeat"),
    ("scale-first.json", "the first run"),
)


def scaling(results: Path) -> tuple[list[str], set[str]]:
    lines = [
        "## How the pool scales",
        "",
        "`aoi3d up --workers K --sites S` on the rotor scene, `mat:70`, a settling time, then "
        "a window of the services' counters, each process's CPU time read from /proc. Newest "
        "run first; each file records its command:",
        "",
    ]
    rows, used = [], set()
    for name, label in SCALE_RUNS:
        d = load(results, name)
        used.add(name)
        lines.append(f"- {label} (`{name}`, {d['cpus']} cores): `{today(d['command'])}`")
        for row in d["rows"]:
            tag = f"{label}, pass {row['pass']}" if "pass" in row and name == "scale.json" \
                else label
            rows.append((tag, row))
    lines += ["", *scale_table(rows), ""]
    lines += ["Speedup of K workers over one, per run (renders/s ÷ the same run's 1 × 1):", ""]
    for name, label in SCALE_RUNS:
        sp = load(results, name)["speedup"]
        parts = [f"{k} {v:.2f}×" for k, v in sp.items() if k not in ("1x1", "by_pass")]
        for p, by in (sp.get("by_pass") or {}).items():
            parts.append(f"pass {p}: " + ", ".join(f"{k} {v:.2f}×" for k, v in by.items()
                                                    if k != "1x1"))
        lines.append(f"- {label}: " + "; ".join(parts))
    d = load(results, "scale.json")
    cores = [[f"{r['workers']} × {r['sites']}, pass {r['pass']}",
              *(f"{_cores(r['cores_by_process'], p):.2f}" for p in
                ("router", "camera", "network", "scheduler", "dispatcher", "metrics", "console")),
              ", ".join(f"{v:.2f}" for k, v in r["cores_by_process"].items()
                        if k.startswith("recon"))] for r in d["rows"]]
    farm = d["farm"]
    lines += [
        "",
        "Where the cores go (`scale.json`, mean cores over the window):",
        "",
        *table(["run", "router", "camera", "network", "scheduler", "dispatcher", "metrics",
                "console", "workers"], cores),
        "",
        f"A farm, from `scale.json`: {farm['sites']} sites × {farm['cameras_per_site']} "
        f"cameras at time scale {farm['time_scale']} take {farm['decisions_per_s']:.1f} "
        f"decisions/s; at {farm['renders_per_s_per_worker']:.2f} renders/s per worker (the "
        f"median single worker) rendering every one takes "
        f"{farm['workers_to_render_every_decision']} worker cores, with "
        f"{farm['router_bytes_per_s'] / 1e6:.1f} MB/s through the edge router ({farm['note']}).",
        "",
    ]
    return lines, used



def _realtime_run(d: dict[str, Any]) -> list[str]:
    """One bench/realtime.py document: its table, the CPU per process and the speedup."""
    rows, cpu_rows = [], []
    procs: list[str] = []
    for r in d["rows"]:
        for p in r["cpu"]["processes"]:
            if p not in procs:
                procs.append(p)
    procs.sort(key=lambda p: (not p.startswith("recon-"), p if p.startswith("recon-") else ""))
    for r in d["rows"]:
        rows.append([r["workers"], f(r["renders_per_s"]),
                     f"{r['rendered_share'] * 100:.1f} %" if r["rendered_share"] else "—",
                     f(r["display_lag_ms_median"], 0), f(r["display_lag_ms_p90"], 0),
                     ci(r["psnr_display_db"]), f(r["pool_wait_ms_mean"], 1),
                     f(r["pool_render_age_ms_mean"], 0), r["superseded"],
                     f"{r['cpu']['recon_share'] * 100:.1f} %",
                     f"{r['load_before'][0]:.2f} → {r['load_after'][0]:.2f}"])
        cpu_rows.append([r["workers"], *(f(r["cpu"]["processes"].get(p, {}).get("core_pct"), 1)
                                         for p in procs), f(r["cpu"]["total_core_pct"], 1)])
    lines = [
        *table(["workers", "renders/s", "rendered", "lag median (ms)", "lag p90 (ms)",
                "PSNR at display (dB)", "pool wait (ms)", "render age (ms)", "superseded",
                "reconstruction's CPU share", "load"], rows),
        "",
        "CPU per process, percent of one core over the window:",
        "",
        *table(["workers", *procs, "all"], cpu_rows),
        "",
    ]
    speedup = d.get("speedup")
    if speedup is not None:
        counts = sorted({r["workers"] for r in d["rows"]})
        pairs = ", ".join(f"{p:.2f}×" for p in d.get("speedup_pairs", []))
        lines += [f"Renders/s of {counts[-1]} workers over {counts[0]}: {speedup:.2f}× (the "
                  f"means of their runs; run by run {pairs}).", ""]
    return lines


_RUN_LINE = re.compile(r"^(?P<label>\S+) (?:\S+ )?(?P<workers>\d+) worker\(s\) at x[\d.]+: "
                       r"(?P<rps>[\d.]+) renders/s, .*display lag median (?P<lag>[\d.]+) / "
                       r"p90 [\d.]+ ms, PSNR at display median (?P<psnr>[\d.]+) dB")
FRESH = "realtime/fresh-wait"
FRESH_LOGS = {"two-workers.log": ("ff1.0", "ff0.5", "AOI3D_DISPATCHER_FRESH_FRACTION 1 ↔ 0.5"),
              "one-worker.log": ("ff1.0", "ff0.5", "AOI3D_DISPATCHER_FRESH_FRACTION 1 ↔ 0.5"),
              "before-after.log": ("OLD", "NEW", "the code before (ef77d61) ↔ after")}
"""The paired runs of the fresh wait: log → (label off, label on, what was switched)."""


def _fresh_pairs(results: Path) -> tuple[list[list[Any]], list[float]]:
    """The fresh wait's paired runs: a table row per log, and every pair's lag change."""
    rows, deltas = [], []
    for log_name, (off, on, what) in FRESH_LOGS.items():
        runs: dict[str, list[re.Match[str]]] = {off: [], on: []}
        for line in (results / FRESH / log_name).read_text().splitlines():
            m = _RUN_LINE.match(line)
            if m and m["label"] in runs:
                runs[m["label"]].append(m)
        pairs = list(zip(runs[off], runs[on], strict=False))

        def arrows(key: str, pairs: list[tuple[re.Match[str], re.Match[str]]] = pairs) -> str:
            return ", ".join(f"{a[key]} → {b[key]}" for a, b in pairs)

        deltas += [float(b["lag"]) - float(a["lag"]) for a, b in pairs]
        rows.append([what, pairs[0][0]["workers"] if pairs else "—", arrows("rps"),
                     arrows("lag"), arrows("psnr")])
    return rows, deltas


def realtime(results: Path) -> tuple[list[str], set[str]]:
    """realtime/realtime.json: ``bench/realtime.py``'s rows, one per worker count; the run
    before the fresh wait (realtime-2026-12-06.json) and the wait's paired runs
    (realtime/fresh-wait/)."""
    name, before = "realtime/realtime.json", "realtime/realtime-2026-12-06.json"
    d, d_before = load(results, name), load(results, before)
    one = next((r for r in d["rows"] if r["workers"] == 1), d["rows"][0])
    fresh_rows, deltas = _fresh_pairs(results)
    waits = {k: load(results, f"{FRESH}/two-workers-ff{k}.json")["rows"][0]["pool_wait_ms_mean"]
             for k in ("1.0", "0.5")}
    lines = [
        "## Real time on two cores",
        "",
        "`aoi3d up --time-scale 1 --workers N` with nothing else changed (the rotor scene, "
        "`mat:70`, the stream carry at 25 steps), each worker count alone: a settling time, "
        "then a window in which renders/s (distinct decisions scored), the share of the "
        "window's decisions rendered, the display lag (display time − decision time, scene "
        "ms), the PSNR at display time and each process's CPU (utime + stime from /proc, with "
        "its children) are read. Pool wait: decision to hand-out; render age: decision to the "
        "render back at the pool (wall ms, means). Load: the 1-minute load average before and "
        f"after ({d['cpus']} CPUs; the pipeline's own threads raise it while it runs).",
        "",
        *redo("make bench-realtime   # = " + d["command"]),
        "",
        f"Measured {d['date']} UTC, the fresh wait on (AOI3D_DISPATCHER_FRESH_FRACTION "
        f"{d['rows'][0].get('fresh_fraction') or 0.5:g}). This VM's speed for the pipeline "
        "drifts by a third within an hour (the code before the wait gave 10.2 renders/s at "
        "112 ms with one worker at 09:56 and 11:27 the same day; this run "
        f"{one['renders_per_s']:.1f} at {one['display_lag_ms_median']:.0f} ms): "
        "compare settings by the paired runs below, not this table against the next.",
        "",
        *_realtime_run(d),
        "**The fresh wait, paired** (`results/realtime/fresh-wait/`, its README has "
        "the commands; 40 s windows, alternated so that the VM's drift hits both alike). A "
        "free worker used to take the pending decision, on average half a decision period "
        "old; it now waits for the next one when the pending one is older than half a period "
        f"(pool wait {waits['1.0']:.1f} → {waits['0.5']:.1f} ms in the two-worker pair's "
        "files):",
        "",
        *table(["runs (2026-12-07 UTC)", "workers", "renders/s, off → on",
                "median lag (ms), off → on", "PSNR at display (dB), off → on"], fresh_rows),
        "",
        f"The median lag changed by {min(deltas):+.1f} to {max(deltas):+.1f} ms over the "
        f"{len(deltas)} pairs. What is left of the lag is the job: a warm start of 25 steps "
        "is about 85 ms of CPU (`python -m bench.recon --carry warm --steps 25 --views 18 "
        "--repeats 30`), and with two workers each has about 70 % of a core beside the "
        "services' half of one.",
        "",
        f"Measured {d_before['date']} UTC, before the fresh wait "
        f"(`results/{before}`):",
        "",
        *_realtime_run(d_before),
    ]
    used = {name, before} | {f"{FRESH}/{p.name}" for p in (results / FRESH).iterdir()}
    return lines, used

def reconstruction(results: Path) -> tuple[list[str], set[str]]:
    """recon-ab.txt: paragraphs (blank-line separated) of ``after``/``before`` lines (JSON),
    each with the comment lines that say when, which commits and in which order."""
    blocks: list[dict[str, Any]] = []
    for para in (results / "recon-ab.txt").read_text().split("\n\n"):
        notes = [ln.lstrip("# ").strip() for ln in para.splitlines() if ln.startswith("#")]
        runs = [(ln.split(" ", 1)[0], json.loads(ln.split(" ", 1)[1]))
                for ln in para.splitlines() if ln.strip() and not ln.startswith("#")]
        if runs:
            blocks.append({"notes": notes, "runs": runs})
    rows = []
    for i, b in enumerate(blocks, 1):
        by: dict[str, dict[str, list[dict[str, Any]]]] = {}
        for side, run in b["runs"]:
            by.setdefault(run["backend"], {"after": [], "before": []})[side].append(run)
        for backend, sides in by.items():
            for a, bf in zip(sides["after"], sides["before"], strict=False):
                rows.append([i, backend, f"{bf['seconds_median']:.2f} s",
                             f"{a['seconds_median']:.2f} s",
                             f"{bf['seconds_median'] / a['seconds_median']:.1f}×",
                             f"{bf['psnr_db']:.3f} → {a['psnr_db']:.3f}"])
    lines = [
        "## One reconstruction, before and after the fused kernels",
        "",
        "The unit of every render: `FieldTrainer` reset → 6 evenly spread views of the rotor "
        "scene → 100 steps of 1024 rays → the held-out view; 96×72, 1 thread. *Before* is "
        "commit 4f43c33 (the last without the fused kernels), *after* the code named in each "
        "block, run alternately on the same machine so that each pair compares.",
        "",
        *redo("python bench/recon.py --repeats 8 --json                 # after",
              "git worktree add /tmp/before 4f43c33",
              "PYTHONPATH=/tmp/before python bench/recon.py --repeats 8 --json   # before",
              "python bench/recon.py --repeats 5 --json --backend ngp    # the other backends"),
        "",
        *table(["block", "backend", "before", "after", "speedup", "PSNR before → after (dB)"],
               rows),
        "",
        "The blocks, as the file records them:",
        "",
    ]
    for i, b in enumerate(blocks, 1):
        lines.append(f"{i}. " + " ".join(b["notes"]))
    lines.append("")
    return lines, {"recon-ab.txt"}


def gpu(results: Path) -> tuple[list[str], set[str]]:
    runs = load_lines(results, "recon-cuda-h200.jsonl")
    steps = sorted({r["steps"] for r in runs})
    backends = list(dict.fromkeys(r["backend"] for r in runs if r["device"] == "cuda"))
    by = {(r["backend"], r["device"], r["steps"]): r for r in runs}
    rows = []
    for b in backends:
        row = [b]
        for s in steps:
            r = by.get((b, "cuda", s))
            row += [f"{r['seconds_median']:.2f} s", f"{r['psnr_db']:.2f} dB"] if r else ["—", "—"]
        rows.append(row)
    for (b, dev, s), r in by.items():
        if dev == "cpu":
            rows.append([f"{b} on the same machine's CPU, {r['threads']} thread (fused kernels)",
                         *([f"{r['seconds_median']:.2f} s", f"{r['psnr_db']:.2f} dB"]
                           if s == steps[0] else ["—", "—"]),
                         *(["—", "—"] * (len(steps) - 1))])
    header = ["backend"]
    for s in steps:
        header += [f"{s} steps, CUDA", "PSNR"]
    live = []
    for name, label in (("scale-h200-cuda.json", "the GPU (both workers sharing it)"),
                        ("scale-h200-cpu.json", "the CPU (1 core each, fused kernels)")):
        row = load(results, name)["rows"][0]
        live.append([label, f(row["renders_per_s"]), f"{row['fraction_rendered'] * 100:.1f} %",
                     f"{row['render_age_s_mean']:.2f} s", ci(row["psnr_db"]),
                     f"{row['decisions_per_s']:.1f}"])
    cpu = load(results, "scale-h200-cpu.json")
    lines = [
        "## On a GPU (one NVIDIA H200)",
        "",
        "One reconstruction with each backend's CUDA path, and the CPU row from the same "
        "machine in the same call:",
        "",
        *redo("python bench/recon.py --device cuda --json --backend NAME [--steps 300]",
              "python bench/recon.py --json    # the CPU row"),
        "",
        *table(header, rows),
        "",
        "The live pipeline at time scale 1 on that machine, 2 workers, the workers' device "
        "set by `AOI3D_RECON_DEVICE` (the files record the command without it):",
        "",
        *redo("AOI3D_RECON_DEVICE=cuda python bench/scale.py --configs 2x1 --time-scale 1 "
              "--settle-s 15 --measure-s 45 --out results/scale-h200-cuda.json",
              "AOI3D_RECON_DEVICE=cpu  python bench/scale.py --configs 2x1 --time-scale 1 "
              "--settle-s 15 --measure-s 45 --out results/scale-h200-cpu.json"),
        "",
        *table(["workers on", "renders/s", "decisions rendered", "render age", "PSNR (dB)",
                "decisions/s"], live),
        "",
        f"The machine: {cpu['cpus']} cores.",
        "",
    ]
    return lines, {"recon-cuda-h200.jsonl", "scale-h200-cuda.json", "scale-h200-cpu.json"}


def pipeline(results: Path) -> tuple[list[str], set[str]]:
    files = sorted(results.glob("pipeline-*.json"), key=lambda p: load(results, p.name)
                   ["time_scale"])
    rows, cmds = [], []
    for p in files:
        d = load(results, p.name)
        drop = 1 - d["frames_delivered_per_s"] / d["frames_offered_per_s"]
        rows.append([
            d["time_scale"], f"{d['frames_generated_per_s']:.1f}",
            f"{d['frames_offered_per_s']:.1f}", f"{d['frames_delivered_per_s']:.1f}",
            f"{drop:.2f}", f"{d['decisions_per_s']:.2f}", f"{d['trainer_steps_per_s']:.0f}",
            f"{ci(d['window_psnr_db'], 1)} ({d['window_psnr_db']['n']})",
            f(d["window_ssim"]["mean"], 3), f(d["window_lpips"]["mean"], 3),
            f(d["window_views"]["mean"], 1),
            f"{d['render_lag_sim_ms']['mean'] / 1000:.2f} / "
            f"{d['render_lag_wall_s']['mean']:.1f}",
            f"{d['camera_ticks_skipped_per_s']:.1f}", f"{d['decisions_skipped_per_s']:.1f}"])
        cmds.append(f"python bench/pipeline.py --policy {d['policy']} --time-scale "
                    f"{d['time_scale']:g} --window-s 60")
    lines = [
        "## The pipeline with one trainer (before the worker pool)",
        "",
        "`aoi3d up` on its own ports with the default scene and `mat:70`; every counter "
        "sampled twice, a window apart. Measured with the single trainer that reconstructed "
        "every render itself, before the pool and the fused kernels (today's rates: \"How the "
        "pool scales\").",
        "",
        *redo(*cmds),
        "",
        *table(["time scale", "frames generated/s", "offered/s", "delivered/s", "drop ratio",
                "decisions/s", "trainer steps/s", "PSNR, dB (renders)", "SSIM", "LPIPS",
                "views", "render lag sim s / wall s", "camera ticks skipped/s",
                "decisions skipped/s"], rows),
        "",
    ]
    return lines, {p.name for p in files}


def channel(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "channel.json")
    rows = [[case, f"{c['camera_slots_per_s_best']:.2e}", f"{c['camera_slots_per_s_median']:.2e}",
             f"{c['seconds_best'] * 1000:.1f} ms"] for case, c in d["cases"].items()]
    lines = [
        "## The channel and AoI simulation",
        "",
        f"{d['cameras']} cameras × {d['duration_ms'] / 1000:.0f} s of `{d['delay']}` links, "
        f"C = {d['period_ms']} ms, best and median of {d['repeats']}; *statistics* computes "
        "the AoI statistics only, *trace* the AoI at every slot. The bench fails below 10⁷ "
        "camera-slots/s.",
        "",
        *redo("python bench/channel.py"),
        "",
        *table(["case", "camera-slots/s (best)", "camera-slots/s (median)", "time (best)"],
               rows),
        "",
        f"Mean AoI in the run: {d['mean_aoi_ms']:.1f} ms.",
        "",
    ]
    return lines, {"channel.json"}


def fields(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "fields.json")
    cfg, m = d["config"], d["machine"]
    budgets = cfg["budgets_s"]
    lines = [
        "## Radiance-field backends",
        "",
        f"Every registered backend trained on frame {cfg['frame']} of "
        f"`{Path(cfg['dataset']).name}` "
        f"({cfg['width']}×{cfg['height']}), PSNR of the held-out view after each training "
        f"budget ({cfg['budget_note']}); {m['threads']} threads, fp32 matmul "
        f"{m['matmul_cpu_gflops_start']:.0f} GFLOP/s at the start; code {d['code_version']}, "
        "which predates the fused kernels (\"One reconstruction\" above has the newer "
        "figures).",
        "",
        *redo("python bench/fields.py"),
        "",
    ]
    for case, c in d["cases"].items():
        ref = c.get("reference") or {}
        rows = []
        for b, r in c["runs"].items():
            pts = {ck["budget_s"]: ck["psnr_db"] for ck in r["checkpoints"]}
            tt = (ref.get("backends") or {}).get(b) if b != ref.get("reference") else None
            rows.append([b, *(f(pts.get(x), 1) for x in budgets),
                         f"{r['rays_per_s'] / 1000:.0f}k", f"{r['render_s_median'] * 1000:.0f} ms",
                         f"{r['memory']['rss_peak_mb']:.0f} MB",
                         f"{tt['time_s']:.0f} s ({tt['speedup']:.1f}×)" if tt else "—"])
        head = [f"{case}: cameras {','.join(map(str, c['cameras']))}" if case != "all"
                else "all 18 cameras"]
        target = ref.get("target_psnr_db")
        lines += [
            f"**{head[0]}** (reference: `{ref.get('reference', '—')}` after "
            f"{ref.get('reference_s', 0):.0f} s, {f(target)} dB)",
            "",
            *table(["backend", *(f"{x:g} s" for x in budgets), "rays/s", "render",
                    "peak RSS", "time to the reference's PSNR"], rows),
            "",
        ]
    return lines, {"fields.json"}


def chaos_judge(d: dict[str, Any], unit: str) -> list[str]:
    """The chaos bench's judge as a one-row table (either target: ``unit`` is what must be
    up at the end, a process or a container)."""
    return table(["faults", "longest recovery (fault's end → next Quality)",
                  "longest gap between Qualities", "stalls over 15 s", "decisions made",
                  "counted by the ledger", "unaccounted", f"every {unit} up at the end"],
                 [[len(d["faults"]), f"{d['max_recovery_s']} s", f"{d['max_quality_gap_s']} s",
                   d["stalls_over_15s"], d["decisions"], d["ledger_decisions"],
                   d["unaccounted"], "yes" if d["all_up_at_end"] else "no"]])


def chaos_faults(d: dict[str, Any], target: str) -> list[str]:
    """Every fault of a chaos run in a folded table."""
    rows = [[f"{x['t_s']:.0f} s", x["kind"], x["target"],
             "—" if x["recovery_s"] is None else f"{x['recovery_s']:.1f} s"]
            for x in d["faults"]]
    return ["<details><summary>The faults</summary>", "",
            *table(["at", "fault", target, "recovery"], rows), "", "</details>"]


def chaos(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "chaos.json")
    led = d["ledger"]["site1"]
    lost = ", ".join(f"`{k}` {v}" for k, v in led["lost"].items() if v)
    lines = [
        "## Faults at random",
        "",
        f"`aoi3d up --workers {d['workers']}` at time scale 1 for {d['minutes']:.0f} minutes; "
        "every 20–40 s one fault (SIGKILL of any process, SIGSTOP of one for 10 s, or a "
        "router restart) while a Zenoh session of the bench's own records every Quality and "
        "every decision made.",
        "",
        *redo(d["command"]),
        "",
        *chaos_judge(d, "process"),
        "",
        f"How the decisions ended (the decision ledger): {led['scored']} scored, "
        + ", ".join(f"{v} {k}" for k, v in led["skipped"].items())
        + f" (skipped by choice), {led['lost_total']} lost — {lost}; {led['open']} open; "
        f"{led['after_close']} events after their decision had ended. Load "
        f"{d['load_1min_at_end']:.2f} at the end.",
        "",
        *chaos_faults(d, "process"),
        "",
    ]
    return lines, {"chaos.json"}


def chaos_multihost(results: Path) -> tuple[list[str], set[str]]:
    if not (results / "chaos-multihost.json").exists():
        return [], set()
    d = load(results, "chaos-multihost.json")
    lines = [
        "## Faults at random across hosts",
        "",
        f"compose.multihost.yaml (an edge host and two worker hosts, Zenoh routers meshed over "
        f"mutual TLS) for {d['minutes']:.0f} minutes; every 20–40 s one fault: a worker "
        "host's router cut off the mesh (`docker network disconnect`, 15 s) and reconnected, "
        "a restart of a router or of an edge service, or a SIGKILL of a worker's process; the "
        "same judge as above.",
        "",
        *redo(d["command"]),
        "",
        *chaos_judge(d, "container"),
        "",
        f"Load {d['load_1min_at_end']:.2f} at the end.",
        "",
        *chaos_faults(d, "target"),
        "",
    ]
    return lines, {"chaos-multihost.json"}


def window_rates(d: dict[str, Any]) -> list[str]:
    """The soak's render rate in each consecutive window (older runs did not record them)."""
    rates = d.get("renders_per_s_by_window")
    if not rates:
        return []
    w = d["window_min"]
    head = [f"{i * w:.0f}–{(i + 1) * w:.0f} min" for i in range(len(rates))]
    return [*table(["", *head], [["renders/s", *(f(r, 3) for r in rates)]]), ""]


def soak(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "soak.json")
    procs = d["processes"]
    names = list(procs)
    rows = [["RSS first 10 min (MiB)", *(f"{procs[n]['rss_start_mib']:.1f}" for n in names)],
            ["RSS last 10 min (MiB)", *(f"{procs[n]['rss_end_mib']:.1f}" for n in names)],
            ["growth", *(f"{procs[n]['growth_pct']:.1f} %" for n in names)],
            ["restarts", *(str(d["restarts"].get(n, "—")) for n in names)]]
    ledgers = [[site, x["decisions"], x["scored"],
                ", ".join(f"{v} {k}" for k, v in x["skipped"].items()),
                x["lost_total"], ", ".join(f"`{k}` {v}" for k, v in x["lost"].items() if v)
                or "—", x["open"]] for site, x in d["ledger"].items()]
    lines = [
        "## An hour's soak",
        "",
        f"`aoi3d up --sites {d['sites']} --workers {d['workers']}`, default scene and time "
        f"scale, {d['minutes']:.0f} minutes; RSS medians of the first and the last "
        f"{d['window_min']:.0f} minutes. Load {d['load_1min_mean']} on average, "
        f"{d['load_1min_max']} at most.",
        "",
        *redo(d["command"]),
        "",
        *table(["", *names], rows),
        "",
        f"Memory within the bound: {'yes' if d['memory_ok'] else 'no'}. {d['renders']} renders; "
        f"{d['renders_per_s_first']} renders/s over the first {d['window_min']:.0f} minutes "
        f"and {d['renders_per_s_last']} over the last (ratio {d['rate_ratio_last_first']}; "
        f"rate within the bound: {'yes' if d['rate_ok'] else 'no'}).",
        "",
        *window_rates(d),
        *table(["site", "decisions", "scored", "skipped", "lost", "lost by reason",
                "open when read"], ledgers),
        "",
    ]
    return lines, {"soak.json"}


def learning(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "scheduler-learning.json")
    s = load(results, "online-live/summary.json")
    lines = [
        "## Online learning",
        "",
        "The scheduler learning online under load (one process, synthetic rewards): "
        "decisions stay on time while PPO updates run off the decision thread.",
        "",
        *redo(f"python bench/scheduler_learning.py --seconds {d['seconds']:g}"),
        "",
        *table(["decisions", "skipped", "lateness median / p99 / max", "updates",
                "update time", "mean reward first → last update", "checkpoints", "load"],
               [[d["decisions"], f"{d['decisions_skipped']:g}",
                 f"{d['lateness_ms']['median']:.1f} / {d['lateness_ms']['p99']:.1f} / "
                 f"{d['lateness_ms']['max']:.1f} ms", f"{d['updates']:g}",
                 f"{d['update_ms_mean']:.0f} ms",
                 f"{d['mean_reward_first_update']:.3f} → {d['mean_reward_last_update']:.3f}",
                 f"{d['checkpoints_written']:g}", f"{d['machine']['loadavg_1min']:.2f}"]]),
        "",
        f"Live, three sites of one pipeline ({s['workers']} workers, time scale "
        f"{s['time_scale']}); first span {s['spans_s']['first'][0] / 60:.0f}–"
        f"{s['spans_s']['first'][1] / 60:.0f} min, last span "
        f"{s['spans_s']['last'][0] / 60:.0f}–{s['spans_s']['last'][1] / 60:.0f} min; load "
        f"{s['load_before'][0]} before, {s['load_after'][0]} after:",
        "",
        *redo(s["command"]),
        "",
    ]
    rows = []
    for site, v in s["sites"].items():
        mr = v.get("minus_rule") or {}
        rows.append([site, v["label"], v["renders"], ci(v["spans"]["first"]["reward"], 3),
                     ci(v["spans"]["last"]["reward"], 3),
                     ci(v["spans"]["last"]["psnr_db"]),
                     f(v["spans"]["last"]["n_views"]["mean"], 1),
                     diff(mr["last"]["reward"], 3) if mr else "—"])
    lines += [*table(["site", "policy", "renders", "reward, first span", "reward, last span",
                      "PSNR last span (dB)", "views last span",
                      "reward − the rule's, last span"], rows), ""]
    return lines, {"scheduler-learning.json", "online-live/summary.json", "online-live/run.json"}


def staleness(results: Path) -> tuple[list[str], set[str]]:
    lines = [
        "## Staleness against views",
        "",
        "A grid field trained 300 steps on frames of a given age from a given number of "
        "views, scored on the held-out view at the same times; the measurement behind the "
        "experiments' choice of scene ([experiments.md](experiments.md)).",
        "",
    ]
    used = set()
    for name in ("staleness-turbine-rotor.json", "staleness-turbine.json"):
        d = load(results, name)
        used.add(name)
        rows = [[r["views"], r["age_frames"], f"{r['age_ms']:.0f}", f(r["psnr_db"]),
                 f(r["ssim"], 3), f(r["lpips"], 3)] for r in d["rows"]]
        lines += [f"**`{d['dataset']}`** (times {', '.join(map(str, d['times']))} ms)", "",
                  *redo(f"python bench/staleness.py --dataset {d['dataset']}"), "",
                  *table(["views", "age (frames)", "age (ms)", "PSNR (dB)", "SSIM", "LPIPS"],
                         rows), ""]
    return lines, used


def dynamic_mask(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "dynamic_mask.json")
    rows = [[r["tau_255"] if r["tau_255"] != d["default_tau_255"] else f"**{r['tau_255']}**",
             f"{r['fraction_mean'] * 100:.1f} %",
             f"{r['fraction_min'] * 100:.1f}–{r['fraction_max'] * 100:.1f} %",
             f"{r['recall_mean']:.3f}", f"{r['off_mean']:.5f}"] for r in d["results"]]
    lines = [
        "## The dynamic region's threshold",
        "",
        f"The held-out view's pixels whose truth changed by more than τ/255 since the truth "
        f"{d['frames_K']} frame periods earlier, dilated by {d['dilation_px']} px, over "
        f"{d['results'][0]['slots']} slots of `{d['dataset']}`; recall of the pixels that "
        f"truly move ({d['moving_fraction_mean'] * 100:.1f} % of the image on average) and "
        "the share marked that does not move. Bold: the default.",
        "",
        *redo(d["command"].strip()),
        "",
        *table(["τ (/255)", "share of the image", "min–max", "recall", "marked, not moving"],
               rows),
        "",
    ]
    return lines, {"dynamic_mask.json"}


def trainer_restart(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "trainer_restart.json")
    rows = [[f"{r['checkpoint_period_s']:g} s" if r["checkpoint_period_s"] else "none",
             f(r["psnr_before_db"]), f(r["psnr_after_db"]),
             f"{r['first_render_after_kill_s']} s", r["renders_averaged"]]
            for r in d["results"]]
    lines = [
        "## The single trainer's restart (historical)",
        "",
        "Before the worker pool, with the `warm` carry: the trainer killed, its model resumed "
        "from a checkpoint or not. The bench left with the single trainer; it is in the "
        "history (`git log --all -- bench/trainer_restart.py`).",
        "",
        *redo(f"python {d['command']}   # at a commit that has it"),
        "",
        *table(["checkpoint period", "PSNR before (dB)", "PSNR after (dB)",
                "first render after the kill", "renders averaged"], rows),
        "",
    ]
    return lines, {"trainer_restart.json"}


def ros2_path(results: Path) -> tuple[list[str], set[str]]:
    runs = [("emulated cameras", "ros2_sweep_emulated.json"),
            ("ROS 2, the robot phase-locked to the pipeline", "ros2_sweep_phase_locked.json"),
            ("ROS 2, the robot at its own phase", "ros2_sweep_free_phase.json"),
            ("emulated cameras, an earlier run", "ros2_sweep_emulated_earlier.json"),
            ("ROS 2 phase-locked, the serial robot", "ros2_sweep_phase_locked_serial.json"),
            ("ROS 2 at its own phase, the serial robot", "ros2_sweep_free_phase_serial.json")]
    loaded = [(label, load(results, name)) for label, name in runs]
    policies = [p["policy"] for p in loaded[0][1]["results"]]
    rows = []
    for policy in policies:
        row: list[Any] = [f"`{policy}`"]
        got = []
        for _, r in loaded:
            p = next(x for x in r["results"] if x["policy"] == policy)
            got.append(p)
            row.append(f"{ci(p['psnr_db'])} ({p['n']})")
        row.append(" / ".join(f(p["cameras_used"]["mean"], 2) for p in got))
        rows.append(row)
    s = loaded[0][1]["settings"]
    lines = [
        "## Real cameras: the ROS 2 path against the emulated cameras",
        "",
        "The live sweep on the emulated cameras, then on the ROS 2 path: the pure-Python robot "
        "(`aoi3d ros2 publish`, rmw_zenoh keys) into `aoi3d up --rig` with the emulated link on "
        "top, same scene; PSNR in dB, mean ± 95 % CI over renders (renders in brackets). "
        "What the differences mean: [real-cameras.md](real-cameras.md).",
        "",
        *redo("bash bench/ros2_sweep.sh --epoch   # emulated, then the robot phase-locked",
              "ROS_ONLY=1 OUT=runs/ros2-free bash bench/ros2_sweep.sh   # the robot at its "
              "own phase"),
        "",
        f"Settings: delay `{s['channel']['delay']}`, carry `{s['carry']}`, "
        f"{s['render_steps']} steps per render, {s['measure_s']:.0f} s windows × "
        f"{s['repeats']} repeats (2026-11-26). The first three columns are the runs with the "
        "robot that sends each frame's cameras together; the last three the earlier runs: the "
        "emulated cameras, and the robot that encoded its cameras one after another (the last "
        "~60 ms wall late).",
        "",
        *table(["policy", *[label for label, _ in loaded],
                "cameras used (same order)"], rows),
        "",
    ]
    return lines, {name for _, name in runs}


def ingest_rate(results: Path) -> tuple[list[str], set[str]]:
    d = load(results, "ingest_rate.json")
    rows = [[r["cameras"], f(r["sent_per_s"], 0), f"{100 * r['published_share']:.1f} %",
             f"{r['periods_skipped']} of {r['periods'] + r['periods_skipped']}", r["lost"],
             r["rejected"], r["inbox_dropped"], f(r["age_ms_median"], 1)]
            for r in d["results"]]
    lines = [
        "## Real cameras in real time: what the ingest takes",
        "",
        "The pure-Python robot at time scale 1 (every camera a raw 96×72 frame each 30 ms) into "
        "`aoi3d up --rig`, the whole pipeline running beside it on the same 2 cores, "
        f"{d['settings']['seconds']} s per camera count ({d['date']}; {d['machine']}). What "
        "it means: [real-cameras.md](real-cameras.md).",
        "",
        *redo(d["command"]),
        "",
        *table(["cameras (with the truth camera)", "images sent /s", "published",
                "robot periods skipped", "lost (sequence gaps)", "refused", "inbox drops",
                "receipt − stamp, median ms"], rows),
        "",
    ]
    return lines, {"ingest_rate.json"}


SECTIONS: tuple[Callable[[Path], tuple[list[str], set[str]]], ...] = (
    live_sweep, live_192, realtime, scaling, reconstruction, gpu, chaos, chaos_multihost, soak,
    pipeline, fields,
    channel, learning, staleness, dynamic_mask, trainer_restart, ros2_path, ingest_rate,
)


#: The folder's index (which command made each entry), not a result.
INDEX = "README.md"


def result_files(results: Path) -> set[str]:
    """Every file under ``results``, as a path relative to it, the index aside."""
    return {p.relative_to(results).as_posix() for p in results.rglob("*")
            if p.is_file() and p != results / INDEX}


def accounted(name: str, used: set[str]) -> bool:
    return name in used or any(name == k or name.startswith(k + "/") for k in ELSEWHERE)


def render(results: Path = RESULTS) -> str:
    """The whole of docs/measurements.md, from the files under ``results``."""
    body: list[str] = []
    used: set[str] = set()
    for section in SECTIONS:
        lines, files = section(results)
        if not lines:  # a section whose results are not there yet
            continue
        body += [*lines, source(*sorted(files)), ""]
        used |= files
    toc = [f"- [{line[3:]}](#{anchor(line[3:])})" for line in body if line.startswith("## ")]
    head = [
        "# Measurements",
        "",
        "<!-- Generated by `python bench/docs.py` (`make docs`) from results/; do not "
        "edit by hand: tests/unit/rules/test_measurements_doc.py fails when this page and the "
        "results disagree. -->",
        "",
        "Every number on this page is read from a file under `results/`, named under "
        "its table, and every table comes with the command that redoes it. What the numbers "
        "mean is in [performance.md](performance.md) and [operations.md](operations.md); the "
        "experiments' claims, re-checked on unseen seeds, are in [science.md](science.md).",
        "Unless a section says otherwise, the machine had 2 cores, no GPU, and other jobs "
        "running: a rerun moves the times by tens of per cent, so only rows measured side by "
        "side compare.",
        "",
        *toc,
        "",
    ]
    others = sorted(n for n in result_files(results) if n not in used)
    tail = ["## Other results", "",
            "Result files this page does not render, and where they are reported:", ""]
    keys = sorted({next(k for k in ELSEWHERE if n == k or n.startswith(k + "/"))
                   for n in others if accounted(n, used)})
    tail += [f"- `results/{k}`: {ELSEWHERE[k]}" for k in keys]
    return "\n".join(head + body + tail) + "\n"


def anchor(title: str) -> str:
    """GitHub's anchor of a heading."""
    keep = "".join(c for c in title.lower() if c.isalnum() or c in " -_")
    return keep.replace(" ", "-")


def unaccounted(results: Path = RESULTS) -> list[str]:
    """Result files that neither a section renders nor ELSEWHERE lists."""
    used: set[str] = set()
    for section in SECTIONS:
        used |= section(results)[1]
    return sorted(n for n in result_files(results) if not accounted(n, used))


def pages(results: Path = RESULTS) -> dict[str, str]:
    """Every generated page: name under docs/ → text."""
    return {PAGE: render(results)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 when a page differs from its regeneration")
    args = ap.parse_args(argv)
    missing = unaccounted(args.results)
    if missing:
        print("results/ files no page reports (render them in bench/docs.py or list "
              "them in ELSEWHERE): " + ", ".join(missing), file=sys.stderr)
        return 1
    stale = []
    for name, text in pages(args.results).items():
        path = args.out / name
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(str(path))
        else:
            args.out.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            print(f"wrote {path}")
    if stale:
        print("stale (run `make docs`): " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
