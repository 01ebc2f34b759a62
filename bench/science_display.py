"""Issue 40 §3: the paper's claims at display time at a budget a viewer would choose.

Called from ``bench/science.py`` (``make science``) and alone with
``python -m bench.science --only display``, which merges into the existing
``claims.json`` / ``docs/science.md``. It runs, on the science seeds and options:

- the four display-time PSNR claims in two more configurations: the streaming carry at its
  live budget (``--carry stream --set render_steps=25``) and the best (Γ, steps) found on
  development seeds (the fresh carry at 50 steps, ``--steps-per-epoch 50``): tradeoff, delay
  and compare (all, mat:best, freshest:6, wait:40) at each;
- the open question "a compute-aware policy beats the best fixed (Γ, steps) in hindsight at
  display time": one compare run (fresh carry, exp:60) over the grid ``mat:Γ@s`` / ``all@s``,
  the compute-aware candidates :data:`COMPUTE_AWARE` and the PPO agent trained with the lag
  in its state on the display-time reward (:data:`PPO_DISPLAY`), with the oracle over
  (Γ, steps) per decision (``oracle:budgets:psnr_display_db``: the grid's cells, from the
  cache) as the bound.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aoi3d.experiment import claims
from aoi3d.experiment.display_claims import compute_aware_beats_best_fixed
from aoi3d.experiment.optimum import optimum
from aoi3d.experiment.oracle import BUDGET_GAMMAS, BUDGET_STEPS
from aoi3d.policy import AllPolicy, Budgeted, MatPolicy, kind_of, parse_policy

CONFIGS: dict[str, tuple[str, tuple[str, ...]]] = {
    "stream25": ("the streaming carry at its live budget (25 steps per render)",
                 ("--carry", "stream", "--set", "render_steps=25")),
    "fresh50": ("the fresh carry at 50 steps (the development seeds' display-time optimum)",
                ("--steps-per-epoch", "50")),
}
"""The two configurations the display-time claims are asked in besides the 300-step runs."""
GRID_GAMMAS = BUDGET_GAMMAS
GRID_STEPS = BUDGET_STEPS
"""The grid: the cells the oracle over (Γ, steps) searches (:mod:`aoi3d.experiment.oracle`)."""
ORACLE = "oracle:budgets:psnr_display_db"
PPO_DISPLAY = "models/ppo/display/final.pt"
"""The PPO agent with the lag to the display in its state, trained on ``reward_display`` with
budgets drawn from the grid's (models/ppo/display/COMMAND), scored at each of them."""
COMPUTE_AWARE = ("dmat:100@50", "dmat:130@50", "dmat:160@50", "dmat:130@100",
                 "deadline:100:20", "deadline:100:40")
"""The compute-aware candidates of the grid run (docs/experiments.md): dmat at the grid's
budgets, deadline at the lags of 50 and 100 steps (time scale 0.1: 18.6 and 35.6 ms)."""


FIGURE_DELAYS = ("exp:20", "exp:100")
"""The delays the fixed grid is also run at for the figure (exp:60 is the question's run)."""


def grid_policies() -> list[str]:
    fixed = [Budgeted(MatPolicy(float(g)), s).spec for s in GRID_STEPS for g in GRID_GAMMAS]
    fixed += [Budgeted(AllPolicy(), s).spec for s in GRID_STEPS]
    return [*fixed, *COMPUTE_AWARE]


def ppo_policies(checkpoint: str | None) -> list[str]:
    """The display-time agent at each budget of the grid (none without a checkpoint)."""
    return [f"ppo:{checkpoint}@{s}" for s in GRID_STEPS] if checkpoint else []


def run_all(exe: str, common: list[str], seeds: int, delay_seeds: int, out: Path,
            runner: Callable[[list[str], list[dict[str, Any]]], float],
            log: list[dict[str, Any]], reuse: bool = False,
            checkpoint: str | None = None) -> None:
    """Every run of this part, each into ``out/display/<name>``; its wall times are kept in
    ``out/display/runs.json``. ``reuse``: a run whose results.json exists is not redone (its
    wall time from runs.json stands). ``checkpoint``: the display-time PPO agent of the grid
    (:data:`PPO_DISPLAY`; None: none)."""
    base = out / "display"
    base.mkdir(parents=True, exist_ok=True)
    runs_file = base / "runs.json"
    kept = json.loads(runs_file.read_text()) if runs_file.exists() else []
    def run(cmd: list[str], log: list[dict[str, Any]]) -> float:
        if reuse and (Path(cmd[cmd.index("--out") + 1]) / "results.json").exists():
            return 0.0
        own: list[dict[str, Any]] = []
        wall = runner(cmd, own)
        log.extend(own)
        shown = {_out_of(r["command"]) for r in own}  # a run redone replaces its old entry
        kept[:] = [r for r in kept if _out_of(r["command"]) not in shown] + own
        runs_file.write_text(json.dumps(kept, indent=1) + "\n")
        return wall

    for name, (_, opts) in CONFIGS.items():
        run([exe, "experiment", "tradeoff", *common, *opts, "--seeds", str(seeds),
             "--gammas", "0,40,70,100,130,160", "--out", str(base / name / "tradeoff")], log)
        run([exe, "experiment", "delay", *common, *opts, "--seeds", str(delay_seeds),
             "--delays", "exp:20,exp:60,exp:100", "--gammas", "40,70,100,130,160",
             "--out", str(base / name / "delay")], log)
        run([exe, "experiment", "compare", *common, *opts, "--seeds", str(seeds),
             "--policy", "all", "--policy", "mat:best", "--policy", "freshest:6",
             "--policy", "wait:40", "--out", str(base / name / "compare")], log)
    grid = [exe, "experiment", "compare", *common, "--seeds", str(seeds), "--no-lpips",
            "--out", str(base / "grid")]
    for p in [*grid_policies(), *ppo_policies(checkpoint), ORACLE]:
        grid += ["--policy", p]
    run(grid, log)
    for delay in FIGURE_DELAYS:  # the figure's other panels: the fixed cells only
        cmd = [exe, "experiment", "compare", *common, "--seeds", str(seeds), "--no-lpips",
               "--delay", delay, "--out", str(base / f"grid-{delay.replace(':', '')}")]
        for p in grid_policies()[:-len(COMPUTE_AWARE)]:
            cmd += ["--policy", p]
        run(cmd, log)


def _out_of(command: str) -> str:
    """The ``--out`` folder of a logged command (what identifies the run), from the results'
    folder on (the same run from another checkout is the same run)."""
    return command.split(" --out ")[-1].split(" ")[0].split("/science/")[-1]


def _load(path: Path) -> dict[str, Any]:
    return dict(json.loads(path.read_text()))


def verdicts(out: Path) -> dict[str, Any]:
    """The display-time claims at each configuration and the grid question, as claims.json
    keeps them (``display_budgets``)."""
    base = out / "display"
    result: dict[str, Any] = {"configs": {}, "runs": []}
    for name, (text, opts) in CONFIGS.items():
        t, d, c = (_load(base / name / f"{k}/results.json")
                   for k in ("tradeoff", "delay", "compare"))
        result["configs"][name] = {
            "text": text, "options": " ".join(opts),
            "steps": t["meta"]["episode_config"]["steps_per_epoch"],
            "verdicts": [v.to_dict() for v in claims.at_display_time(t, d, c)]}
    grid = _load(base / "grid/results.json")
    ppo = [r["policy"] for r in grid["policies"] if kind_of(r["policy"]).kind == "ppo"]
    verdict = compute_aware_beats_best_fixed(grid, aware_labels=ppo).to_dict()
    root = str(Path(__file__).resolve().parent.parent) + "/"  # checkpoints as the repo names them
    result["grid"] = json.loads(json.dumps(verdict).replace(root, ""))
    runs = base / "runs.json"
    result["runs"] = json.loads(runs.read_text()) if runs.exists() else []
    return result


def render_lines(section: dict[str, Any], rel: str) -> list[str]:
    """The science.md section of this part."""
    lines = ["", "## The claims at display time, at a budget a viewer would choose",
             "", "The four display-time PSNR claims asked again in two more configurations, "
             "same seeds and options as the 300-step runs (compare: all, mat:best, "
             "freshest:6, wait:40). Reported either way; they do not decide the exit status.",
             "", "| configuration | claim | verdict | evidence |", "|---|---|---|---|"]
    for name, cfg in section["configs"].items():
        for v in cfg["verdicts"]:
            lines.append(f"| {name}: {cfg['text']} (`{cfg['options']}`) | {v['statement']} | "
                         f"{'**holds**' if v['holds'] else '**fails**'} | {v['evidence']} |")
    g = section["grid"]
    lines += ["", "**Open question** — compute-aware against the best fixed (Γ, steps) in "
              "hindsight (fresh carry, exp:60, the grid `mat:Γ@s` / `all@s`, Γ ∈ "
              f"{', '.join(map(str, GRID_GAMMAS))}, s ∈ {', '.join(map(str, GRID_STEPS))}, "
              f"and {', '.join(f'`{p}`' for p in COMPUTE_AWARE)}, and PPO with the lag in its "
              f"state trained on reward_display (`{PPO_DISPLAY}`) at each budget; the bound "
              f"`{ORACLE}`; psnr_display_db):", "",
              "| question | answer | evidence |", "|---|---|---|",
              f"| {g['statement']}? | {'**yes**' if g['holds'] else '**no**'} | "
              f"{g['evidence']} |", "",
              "Expected from first principles: on the virtual clock the lag has no queue, so "
              "`dmat:Γ@s` selects as a MAT with Γ shifted by the constant lag and `deadline` "
              "picks a constant budget; each is a fixed (Γ, s) cell, so neither can beat the "
              "best cell in hindsight by more than noise. At one budget L is a constant too, "
              "so PPO with L in its state can only gain by selecting better than MAT, not by "
              "reading L. The room is the per-seed best cell's mean lead over the best cell; "
              "the oracle's is the best cell per *decision* (searched with the truth at "
              "display time: a bound, not a policy).", "",
              "| grid cell | display-time PSNR (dB) |", "|---|---|"]
    means = dict(g["numbers"].get("means", {}))
    if "oracle_mean" in g["numbers"]:
        means[f"{g['numbers']['oracle']} (bound)"] = g["numbers"]["oracle_mean"]
    for p, m in sorted(means.items(), key=lambda kv: -kv[1]):
        lines.append(f"| `{p}` | {m:.2f} |")
    if section["runs"]:
        lines += ["", "Wall time of each run (2 cores shared with other sessions, load at "
                  "start/end; each run reuses the episode cache the runs before it "
                  "filled): " + "; ".join(
            f"`{r['command'].split(' --out ')[-1].split(' --')[0].split('/science/')[-1]}` "
            f"{r['wall_s']} s "
            f"({r['load_at_start']}/{r['load_at_end']})" for r in section["runs"]) + "."]
    lines += ["", f"Figure: `docs/figures/display_budgets.png`; outputs `{rel}/display/`. "
              "Redo only this part: `python -m bench.science --only display`.", ""]
    return lines


def _cells(episodes: list[dict[str, Any]], delay: str, steps_of: Callable[[str], int | None],
           steps: int) -> dict[float, dict[int, float]]:
    cells: dict[float, dict[int, float]] = {}
    for e in episodes:
        if e.get("delay", delay) != delay or steps_of(e["policy"]) != steps:
            continue
        kind = kind_of(e["policy"]).kind
        if kind not in ("mat", "all"):
            continue
        g = math.inf if kind == "all" else getattr(parse_policy(e["policy"]), "gamma_ms", math.nan)
        cells.setdefault(float(g), {})[e["seed"]] = e[claims.DISPLAY_METRIC]
    return cells


def figure(out: Path, dest: Path) -> None:
    """Display-time PSNR over Γ × budget, one panel per delay; a cell is framed when it is in
    the display-time optimum set of its row and the row's optimum is interior is written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = out / "display"
    rows: list[tuple[str, Path, int, Callable[[str], int | None]]] = [
        ("fresh, 300 steps", out / "delay/results.json", 300, lambda p: 300),
        ("fresh, 50 steps", base / "fresh50/delay/results.json", 50, lambda p: 50),
        ("stream, 25 steps", base / "stream25/delay/results.json", 25, lambda p: 25)]
    def budget(p: str) -> int | None:
        return int(p.split("@")[1]) if "@" in p else None

    delays = ("exp:20", "exp:60", "exp:100")
    grids = {d: base / (f"grid-{d.replace(':', '')}" if d in FIGURE_DELAYS else "grid")
             / "results.json" for d in delays}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, delay in zip(axes, delays, strict=True):
        labels, data, marks = [], [], []
        grid = [(f"fresh, {s} steps (grid)", grids[delay], s, budget) for s in GRID_STEPS]
        for label, path, steps, steps_of in rows + grid:
            if not path.exists():
                continue
            doc = _load(path)
            cells = _cells(doc["episodes"], delay, steps_of, steps)
            cols = [g for g in (40.0, 70.0, 100.0, 130.0, 160.0, math.inf) if g in cells]
            if not cols:
                continue
            opt = optimum(cells, metric=claims.DISPLAY_METRIC, ordered=True)
            members = set(opt.members)
            labels.append(f"{label}{' — interior' if opt.interior else ''}")
            data.append([sum(cells[g].values()) / len(cells[g]) if g in cells else math.nan
                         for g in (40.0, 70.0, 100.0, 130.0, 160.0, math.inf)])
            marks.append([g in members for g in (40.0, 70.0, 100.0, 130.0, 160.0, math.inf)])
        im = ax.imshow(data, aspect="auto", cmap="viridis")
        for i, row in enumerate(marks):
            for j, m in enumerate(row):
                v = data[i][j]
                if not math.isnan(v):
                    ax.text(j, i, f"{v:.1f}{'*' if m else ''}", ha="center", va="center",
                            color="w" if not m else "k",
                            bbox={"fc": "w", "ec": "k"} if m else None, fontsize=8)
        ax.set_xticks(range(6), ["40", "70", "100", "130", "160", "all"])
        ax.set_yticks(range(len(labels)), labels, fontsize=8)
        ax.set_xlabel("Γ (ms)")
        ax.set_title(f"{delay}: display-time PSNR (dB)")
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle("Where the tradeoff holds at display time: boxed * = in the optimum set "
                 "(not significantly worse than the best of its row); 'interior' = the set "
                 "holds neither end")
    fig.tight_layout()
    dest.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(dest, dpi=110)
    plt.close(fig)
