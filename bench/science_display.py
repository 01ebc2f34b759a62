"""Issue 40 §3: the paper's claims at display time at a budget a viewer would choose.

Called from ``bench/science.py`` (``make science``) and alone with
``python -m bench.science --only display``, which merges into the existing
``claims.json`` / ``docs/science.md``. It runs, on the science seeds and options:

- the four display-time PSNR claims in two more configurations: the streaming carry at its
  live budget (``--carry stream --set render_steps=25``) and the best (Γ, steps) found on
  development seeds (the fresh carry at 50 steps, ``--steps-per-epoch 50``): tradeoff, delay
  and compare (all, mat:best, freshest:6, wait:40) at each;
- the open question "a compute-aware policy beats the best fixed (Γ, steps) in hindsight at
  display time": one compare run (fresh carry, exp:60) over the grid ``mat:Γ@s`` / ``all@s``
  and the compute-aware candidates :data:`COMPUTE_AWARE`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

CONFIGS: dict[str, tuple[str, tuple[str, ...]]] = {
    "stream25": ("the streaming carry at its live budget (25 steps per render)",
                 ("--carry", "stream", "--set", "render_steps=25")),
    "fresh50": ("the fresh carry at 50 steps (the development seeds' display-time optimum)",
                ("--steps-per-epoch", "50")),
}
"""The two configurations the display-time claims are asked in besides the 300-step runs."""
GRID_GAMMAS = (40, 70, 100, 130, 160)
GRID_STEPS = (25, 50, 100)
COMPUTE_AWARE = ("dmat:100@50", "dmat:130@50", "dmat:160@50", "dmat:130@100",
                 "deadline:100:20", "deadline:100:40")
"""The compute-aware candidates of the grid run (docs/experiments.md): dmat at the grid's
budgets, deadline at the lags of 50 and 100 steps (time scale 0.1: 18.6 and 35.6 ms)."""


def grid_policies() -> list[str]:
    fixed = [f"mat:{g}@{s}" for s in GRID_STEPS for g in GRID_GAMMAS]
    fixed += [f"all@{s}" for s in GRID_STEPS]
    return [*fixed, *COMPUTE_AWARE]


def run_all(exe: str, common: list[str], seeds: int, delay_seeds: int, out: Path,
            run: Callable[[list[str], list[dict[str, Any]]], float],
            log: list[dict[str, Any]]) -> None:
    """Every run of this part, each into ``out/display/<name>``."""
    base = out / "display"
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
    for p in grid_policies():
        grid += ["--policy", p]
    run(grid, log)
