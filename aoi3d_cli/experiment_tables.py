"""What ``aoi3d experiment`` prints: the tables of rows, the optimum sets, the delay table and
an oracle bound's distances (the numbers are :mod:`aoi3d.experiment`'s)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from rich.table import Table

from aoi3d.metric import BY_NAME, LIVE, PSNR, PSNR_DYNAMIC, REWARD
from aoi3d_cli.common import fmt, short_label
from aoi3d_cli.experiment_shared import console

if TYPE_CHECKING:
    from aoi3d.experiment.optimum import Optimum


def print_rows(rows: Sequence[dict[str, Any]], first: str, title: str) -> None:
    """One row per point or policy: the quality metrics (mean ± 95% CI), cameras, AoI."""
    table = Table(title=title)
    for name in (first, "n", "PSNR (dB)", "dynamic PSNR (dB)", "SSIM", "LPIPS", "reward",
                 "cameras", "AoI used (ms)"):
        table.add_column(name, justify="right")
    for r in rows:
        table.add_row(str(r[first]), str(r["n"]),
                      *(fmt(r[m], r[f"{m}_ci95"], BY_NAME[m].digits) for m in LIVE),
                      fmt(r["n_selected"], None, 1), fmt(r["aoi_used_ms"], None, 0))
    console.print(table)


def _fmt_candidates(members: Sequence[Any]) -> str:
    return ", ".join(f"{m:g}" if isinstance(m, float) else str(m) for m in members)


def print_optima(optima: dict[str, Optimum], unit: str = "Γ") -> None:
    """Per metric, the best candidate and the optimum set (interior or not)."""
    for metric, opt in optima.items():
        if opt.ends:
            inside = [e for e in opt.ends if e in opt.members]
            verdict = ("[green]interior[/]" if opt.interior else
                       f"[yellow]not interior[/] ({_fmt_candidates(inside)}, an end of the "
                       f"sweep, is not significantly worse)")
        else:
            verdict = ""
        console.print(f"{metric}: best {unit} = {_fmt_candidates([opt.best])}; optimum set "
                      f"(not significantly worse, paired over {len(opt.seeds)} seeds): "
                      f"{{{_fmt_candidates(opt.members)}}} {verdict}")


def print_delay_optima(optima: Sequence[dict[str, Any]], metric: str, seed_span: str) -> None:
    """The optimal Γ per delay and its optimum set."""
    table = Table(title=f"optimal Γ per delay (best mean {metric}; seeds {seed_span})")
    for name in ("delay", "E[Y] (ms)", "best Γ (ms)", metric,
                 "optimum set: Γ not significantly worse (paired)", "interior"):
        table.add_column(name, justify="right")
    for o in optima:
        table.add_row(o["delay"], f"{o['mean_delay_ms']:g}", f"{o['best_gamma_ms']:g}",
                      fmt(o["best_value"], o["best_ci95"], 3),
                      f"{o['optimum_min_ms']:g}–{o['optimum_max_ms']:g}",
                      "yes" if o["interior"] else "no")
    console.print(table)


def print_bound(spec: str, doc: dict[str, Any]) -> None:
    """An oracle bound's cost and each policy's paired distance to it."""
    cost = doc["cost"]
    per = cost["reconstructions_per_decision"]
    console.print(
        f"[bold]{spec}[/] is a bound (searched with the truth), not a policy: "
        f"{cost['reconstructions']} reconstructions over {cost['decisions']} decisions "
        f"({per['mean']:.1f} per decision, {per['min']}–{per['max']}), "
        f"{cost['compute_s']:.0f} s of compute")
    table = Table(title=f"{spec} − policy (paired; positive: the bound is better)")
    table.add_column("policy")
    shown = (PSNR, PSNR_DYNAMIC, REWARD)
    for m in shown:
        table.add_column(m.name, justify="right")
    for p in doc["minus"][PSNR.name]:
        table.add_row(short_label(p), *(fmt(doc["minus"][m.name][p]["mean"],
                                             doc["minus"][m.name][p]["ci95"], m.digits)
                                         for m in shown))
    console.print(table)
