"""Issue 41's question, run: the static grid against the time-aware ``flow`` field over MAT Γ,
at decision and display time, at two links, on the same seeds (aoi3d/experiment/timefield.py
states the arms, the analysis and the goal).

For each link and arm it runs ``aoi3d experiment tradeoff`` (the quick preset's episode,
LPIPS off), measures the CPU seconds per render of every arm (interleaved reconstructions on
the experiments' scene, frames 1–4 frames old), and writes ``<out>/timefield.json`` (the
numbers, the verdicts, the CPU seconds), ``<out>/timefield.png`` (both tradeoff curves) and
every command's folder under ``<out>/<link>/<arm>/``. ``make science`` asks it on its unseen
seeds (``bench/science.py``, ``--timefield-seeds``); alone:

    python -m bench.timefield --seeds 2 --seed-offset 10 --processes 2    # development seeds
    python -m bench.timefield --science --processes 2   # make science's seeds, its files only

``--science`` runs it as ``make science`` does (seeds 20000–20007, its cache, into
``results/science/timefield``) and puts the verdicts, numbers and section into
``results/science/claims.json`` and ``docs/science.md`` (replacing its own part, the
rest as ``make science`` last wrote it), without re-running the other claims.

Cost: 6 arms × 6 Γ × 2 links × S seeds × 4 scored decisions of 16–100 steps: with 8 seeds
about 2,300 reconstructions, 12.0 minutes of wall time on the 2-core machine with 2 processes,
busy with other jobs for the first half (docs/experiments.md, "Does a time-aware field move
the tradeoff?").
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aoi3d.experiment import timefield as tf
from bench import common
from bench.common import ROOT

Runner = Callable[[list[str]], Any]


def measure_cpu(dataset: Path, repeats: int = 6) -> dict[str, float]:
    """Median CPU seconds per render of every arm: its reconstruction (a fresh one, or a warm
    start 10 frames after the previous decision) and one render, 9 views of frames 1–4
    frames old, one thread; the arms interleaved so that the machine's load falls on all."""
    from aoi3d.field import FieldTrainer, TrainView, field_config
    from aoi3d.field.carry import Reconstruction, WarmStart
    from aoi3d.field.process import configure_process
    from aoi3d.scene import open_dataset

    configure_process(1)
    ds = open_dataset(dataset)
    cams = list(ds.train_ids)[::2]
    heldout = ds.cameras[ds.heldout_id]
    frame_ms = 1000.0 / ds.fps

    def views(t0: int) -> list[TrainView]:
        return [TrainView(ds.cameras[c], ds.frame(c, (t0 - 1 - i % 4) % ds.n_frames),
                          age_ms=(1 + i % 4) * frame_ms) for i, c in enumerate(cams)]

    recs = {}
    for arm in tf.ARMS:
        trainer = FieldTrainer(field_config(arm.backend), ds.aabb, device="cpu", seed=0)
        recs[arm.name] = Reconstruction(
            trainer, arm.carry, arm.steps, WarmStart(cold_steps=arm.cold_steps or arm.steps))
    cpu: dict[str, list[float]] = {a.name: [] for a in tf.ARMS}
    for k in range(repeats + 1):
        t0 = 40 + 10 * k
        for arm in tf.ARMS:
            rec = recs[arm.name]
            started = time.process_time()
            rec.render_decision(heldout, views(t0), time_ms=t0 * frame_ms)
            if k > 0 or arm.carry == "fresh":  # a stream arm's first decision is its cold one
                cpu[arm.name].append(time.process_time() - started)
    return {name: round(statistics.median(v), 4) for name, v in cpu.items()}


def parameter_counts(dataset: Path) -> dict[str, int]:
    """Parameters of each backend's field as a 100-step reconstruction leaves it."""
    from aoi3d.field import field_config
    from aoi3d.scene import open_dataset

    box = open_dataset(dataset).aabb
    return {b: sum(p.numel() for p in field_config(b).build(box).parameters())
            for b in ("grid", "flow")}


def dataset_of(extra: list[str]) -> Path:
    """The dataset the commands get (``--dataset=PATH`` among ``extra``, else the
    experiments' scene)."""
    for option in extra:
        if option.startswith("--dataset="):
            return Path(option.partition("=")[2])
    return ROOT / "data/turbine-rotor"


def run_question(runner: Runner, exe: str, common: list[str], out: Path, seeds: int,
                 extra: list[str], dataset: Path, cost_repeats: int = 6) -> dict[str, Any]:
    """Run every arm at every link (``runner`` runs one command), measure the CPU seconds,
    analyse, plot; returns the document written to ``<out>/timefield.json``."""
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    docs: dict[str, dict[str, Any]] = {}
    for delay in tf.DELAYS:
        for arm in tf.ARMS:
            folder = out / delay.replace(":", "") / arm.name
            runner([exe, "experiment", "tradeoff", *common, "--seeds", str(seeds),
                    "--gammas", ",".join(str(g) for g in tf.GAMMAS), "--delay", delay,
                    "--no-lpips", *arm.options(), *extra, "--out", str(folder)])
            docs.setdefault(delay, {})[arm.name] = json.loads(
                (folder / "results.json").read_text())
    analysis = tf.analyse(docs)
    cpu = measure_cpu(dataset, cost_repeats) if cost_repeats > 0 else {}
    ratios = {a.level: round(cpu[tf.twin(a).name] / cpu[a.name], 3)
              for a in tf.ARMS if not a.time_aware and cpu}
    verdicts = [tf.goal(analysis, d) for d in tf.DELAYS]
    doc = {"arms": tf.describe(), "delays": list(tf.DELAYS), "gammas": list(tf.GAMMAS),
           "flow_step_cost": tf.FLOW_STEP_COST, "cpu_seconds_per_render": cpu,
           "cpu_ratio_time_aware_over_static": ratios,
           "load_after": round(os.getloadavg()[0], 2),
           "parameters": parameter_counts(dataset),
           "verdicts": [v.to_dict() for v in verdicts], "analysis": tf.public(analysis),
           "wall_s": round(time.perf_counter() - started, 1)}
    (out / "timefield.json").write_text(json.dumps(doc, indent=2, default=str) + "\n")
    tf.plot(analysis, out / "timefield.png")
    return doc


def markdown(doc: dict[str, Any], rel: str) -> list[str]:
    """science.md's section on the question."""
    lines = ["", "## A time-aware field", "",
             "The static grid against the time-aware `flow` field (the grid carried by a learned "
             "velocity field, rendered at the time asked for: aoi3d/field/flow.py) on the same "
             "seeds and episodes, LPIPS off. Equal CPU seconds per render: a flow step costs "
             f"{doc['flow_step_cost']:g} grid steps, so each static arm has a time-aware twin "
             f"with 1/{doc['flow_step_cost']:g} of its steps. Measured here (CPU seconds per "
             "render, median of interleaved reconstructions): "
             + ", ".join(f"{k} {v:.3f} s" for k, v in doc["cpu_seconds_per_render"].items())
             + "; time-aware / static at each level: "
             + ", ".join(f"{k} {v:.2f}" for k, v in
                         doc["cpu_ratio_time_aware_over_static"].items())
             + f". Fields: {tf.parameters(doc['parameters'])}.", "",
             f"Seeds {_seeds(doc)}; {doc.get('wall_s', 0) / 60:.1f} min of wall time (load "
             f"{doc.get('load_after', '—')} at the end). Redo: `make science`, or this part "
             "alone: `python -m bench.timefield --science`.", "",
             "![both tradeoff curves](figures/timefield.png)", "",
             "| question | answer | evidence |", "|---|---|---|"]
    for v in doc["verdicts"]:
        lines.append(f"| {v['statement']}? | {'**yes**' if v['holds'] else '**no**'} | "
                     f"{v['evidence']} |")
    for delay, d in doc["analysis"].items():
        lines += ["", f"**{delay}** — best Γ and the optimum set of each arm (dynamic-region "
                  "PSNR at display time; PSNR at decision time), and per CPU level the "
                  "time-aware arm's best minus the static arm's, paired (dB):", "",
                  "| arm | dyn. PSNR @display, best Γ (dB) | optimum set | interior | "
                  "PSNR @decision, best Γ | interior | display − decision (dB) |",
                  "|---|---|---|---|---|---|---|"]
        for a in d["arms"].values():
            best = a["best"][tf.DISPLAY]
            row = next(r for r in a["rows"] if r["gamma"] == best)
            best_d = a["best"]["psnr_db"]
            row_d = next(r for r in a["rows"] if r["gamma"] == best_d)
            o, od = a["optimum"][tf.DISPLAY], a["optimum"]["psnr_db"]
            g = a["display_gain"]
            lines.append(f"| {a['arm']} | {best}: {row[tf.DISPLAY]:.2f} | "
                         f"{{{', '.join(_g(m) for m in o['members'])}}} | "
                         f"{'yes' if o['interior'] else 'no'} | {best_d}: "
                         f"{row_d['psnr_db']:.2f} | {'yes' if od['interior'] else 'no'} | "
                         f"{g['mean']:+.2f} ± {g['ci95']:.2f} |")
        lines += ["", "| CPU level | " + " | ".join(_METRIC_NAMES.values()) + " |",
                  "|---|" + "---|" * len(_METRIC_NAMES)]
        for level, m in d["levels"].items():
            lines.append(f"| {level} | " + " | ".join(
                f"{m[k]['mean']:+.2f} ± {m[k]['ci95']:.2f}" for k in _METRIC_NAMES) + " |")
    lines += ["", f"Outputs: `{rel}/timefield/` (every arm's tradeoff, `timefield.json`).", ""]
    return lines


_METRIC_NAMES = {"psnr_db": "PSNR @decision", "psnr_dynamic_db": "dyn. @decision",
                 "psnr_display_db": "PSNR @display", tf.DISPLAY: "dyn. @display",
                 "psnr_static_db": "static region @decision"}


def _seeds(doc: dict[str, Any]) -> str:
    seeds = sorted({s for d in doc["analysis"].values() for a in d["arms"].values()
                    for s in a["seeds"]})
    return f"{seeds[0]}–{seeds[-1]}" if len(seeds) > 1 else str(seeds[0]) if seeds else "—"


def _g(value: Any) -> str:
    return "all" if value == "all" else f"{float(value):g}"


SECTION = "## A time-aware field"


def update_science(doc: dict[str, Any], claims_path: Path, science_md: Path,
                   figures: Path) -> None:
    """Put the question's part into ``make science``'s outputs: claims.json's ``time_aware``
    and its verdicts among the ``questions`` (replacing earlier ones), science.md's section
    (replacing it), the figure."""
    from aoi3d.experiment.claims import Verdict

    claims = json.loads(claims_path.read_text())
    ids = {v["claim"] for v in doc["verdicts"]}
    claims["questions"] = [q for q in claims.get("questions", []) if q["claim"] not in ids]
    claims["questions"] += [Verdict(**v).to_dict() for v in doc["verdicts"]]
    claims["time_aware"] = doc
    claims_path.write_text(json.dumps(claims, indent=2, default=str) + "\n")
    text = science_md.read_text()
    if SECTION in text:
        text = text[:text.index(SECTION)].rstrip("\n") + "\n"
    rel = os.path.relpath(claims_path.parent, ROOT)
    science_md.write_text(text + "\n".join(markdown(doc, rel)))
    figures.mkdir(parents=True, exist_ok=True)
    (figures / "timefield.png").write_bytes((claims_path.parent / "timefield/timefield.png")
                                            .read_bytes())


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--seed-offset", type=int, default=10,
                    help="first seed (default 10: development seeds)")
    ap.add_argument("--processes", "--workers", dest="processes", type=int, default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "results/timefield")
    ap.add_argument("--cache", type=Path, default=ROOT / "runs/experiments/timefield-cache")
    ap.add_argument("--dataset", type=Path, default=ROOT / "data/turbine-rotor")
    ap.add_argument("--cost-repeats", type=int, default=6,
                    help="reconstructions per arm for the CPU seconds (0: skip)")
    ap.add_argument("--science", action="store_true",
                    help="as make science asks it: seeds 20000-20007, its cache and folder; "
                         "updates claims.json and docs/science.md (see above)")
    common.add_json_option(ap)
    return ap


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The question for ``parser()``'s options (its commands' output on stderr under
    ``--json``); with ``--science`` into make science's outputs. Returns its document."""
    if args.science:
        args.seeds, args.seed_offset = 8, 20000
        args.out = ROOT / "results/science/timefield"
        args.cache = ROOT / "runs/experiments/science-cache"
    exe = str(Path(sys.executable).with_name("aoi3d"))
    if not Path(exe).exists():
        exe = "aoi3d"
    flags = ["--preset", "quick", "--cache", str(args.cache), "--seed-offset",
             str(args.seed_offset), "--dataset", str(args.dataset)]
    if args.processes:
        flags += ["--processes", str(args.processes)]
    out_to = sys.stderr if args.json else None
    doc = run_question(lambda cmd: subprocess.run(cmd, check=True, stdout=out_to), exe, flags,
                       args.out, args.seeds, [], args.dataset, args.cost_repeats)
    if args.science:
        update_science(doc, args.out.parent / "claims.json", ROOT / "docs/science.md",
                       ROOT / "docs/figures")
    return doc


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    started = time.perf_counter()
    with common.progress_to_stderr(args.json):
        doc = run(args)
        for v in doc["verdicts"]:
            print(f"{'YES' if v['holds'] else 'NO '}  {v['statement']}: {v['evidence']}")
        print(f"{(time.perf_counter() - started) / 60:.1f} min; {args.out / 'timefield.json'}")
    if args.json:
        common.print_json(doc, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
