"""``aoi3d replay``: re-run a recording (``aoi3d up --record``) on the virtual clock.

Under the recorded policy it checks that the recording reproduces: every decision's
selection, and every scored render's PSNR, SSIM, LPIPS and reward, rebuilt with the live
worker's and metrics service's own code (:mod:`services.recorder.replay`). With ``--policy``
it also gives each other policy's counterfactual on the same arrivals, paired by decision
epoch with the recorded policy's replayed scores (docs/recording.md).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

import typer

from aoi3d.cli.common import fail, fmt, make_console


def _paired(a: list[float], b: list[float]) -> dict[str, float | int | None]:
    """Mean of a − b and its Student-t 95% half-width (None below two pairs)."""
    import numpy as np
    from scipy import stats

    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    if d.size == 0:
        return {"n": 0, "mean": None, "ci95": None}
    half = (float(stats.t.ppf(0.975, d.size - 1) * d.std(ddof=1) / math.sqrt(d.size))
            if d.size > 1 else None)
    return {"n": int(d.size), "mean": float(d.mean()), "ci95": half}


def _summary(result, baseline) -> dict:
    """Means over the rebuilt decisions and the paired differences to ``baseline``."""
    import numpy as np

    def quality(r):
        return {(d.site, d.key): d for d in r.decisions if d.quality is not None}

    mine, base = quality(result), quality(baseline)
    keys = [k for k in mine if k in base]
    out: dict = {"policy": result.policy, "n": len(keys)}
    for name in ("psnr_db", "ssim", "lpips", "reward"):
        vals = [getattr(mine[k].quality, name) for k in keys
                if name != "lpips" or mine[k].quality.HasField("lpips")]
        out[name] = float(np.mean(vals)) if vals else None
        if name != "lpips" or (vals and len(vals) == len(keys)):
            out[f"{name}_vs_recorded"] = _paired(
                [getattr(mine[k].quality, name) for k in keys],
                [getattr(base[k].quality, name) for k in keys])
    out["cameras_used"] = float(np.mean([len(mine[k].selected) for k in keys])) if keys \
        else None
    aoi = [mine[k].mean_aoi_selected_ms for k in keys
           if math.isfinite(mine[k].mean_aoi_selected_ms)]
    out["aoi_selected_ms"] = float(np.mean(aoi)) if aoi else None
    return out


def replay(
    recording: Annotated[Path, typer.Argument(
        help="The MCAP file `aoi3d up --record` wrote (its .partN segments follow it).")],
    policy: Annotated[list[str] | None, typer.Option(
        "--policy", help="A policy to replay the same arrivals under (all, mat:70, "
                         "freshest:6, wait:40, ppo:PATH); repeat it or give a comma list "
                         "for a paired table against the recorded policy.")] = None,
    json_out: Annotated[bool, typer.Option(
        "--json", help="Print one JSON object instead of tables.")] = False,
    site: Annotated[list[str] | None, typer.Option(
        help="Replay these sites only (default: every site in the recording).")] = None,
    max_renders: Annotated[int | None, typer.Option(
        min=0, help="Rebuild at most this many scored decisions per site (default: all; "
                    "each is one reconstruction, about half a second on one core).")] = None,
    score: Annotated[bool, typer.Option(
        help="Rebuild and score the renders (--no-score: compare the selections only).")]
    = True,
    threads: Annotated[int | None, typer.Option(
        min=1, help="Torch threads of the reconstruction (default: the recorded workers').")]
    = None,
) -> None:
    """Re-run a recording on the virtual clock with its recorded frames, generation and
    arrival times: under the recorded policy it must reproduce every selection and every
    score; under --policy P the counterfactual on the same arrivals, paired by epoch."""
    from services.recorder.replay import load, score_diffs
    from services.recorder.replay import replay as run_replay

    console = make_console(stderr=json_out)
    specs = [s.strip() for p in (policy or []) for s in p.split(",") if s.strip()]
    from aoi3d.policy import PolicySpecError, parse_policy

    for spec in specs:
        try:
            parse_policy(spec)
        except PolicySpecError as err:
            raise typer.BadParameter(str(err), param_hint="'--policy'") from None
    try:
        rec = load(recording)
    except (FileNotFoundError, OSError) as err:
        fail(err)
    except Exception as err:  # a damaged file: the mcap reader's own errors
        fail(f"{recording} cannot be read as an MCAP recording: {err}")
    missing = [s for s in (site or []) if s not in rec.sites]
    if missing:
        fail(f"no site {', '.join(missing)} in the recording; it holds "
             f"{', '.join(sorted(rec.sites)) or 'none'}")
    scorers: dict = {}
    kwargs = dict(sites=site, score=score, max_renders=max_renders, threads=threads,
                  scorers=scorers)
    try:
        base = run_replay(rec, None, **kwargs)
        others = [run_replay(rec, spec, **kwargs) for spec in specs]
    except (ValueError, PolicySpecError) as err:
        fail(err)
    diffs = score_diffs(rec, base)
    doc = {
        "recording": str(recording), "files": [str(f) for f in rec.files],
        "sites": sorted(site or rec.sites),
        "recorded_policies": sorted({d.policy for s in rec.sites.values()
                                     for d in s.decisions}),
        "policy": "recorded",
        "decisions": len(base.decisions),
        "selections_equal": base.selections_equal,
        "aoi_vectors_equal": sum(d.aoi_equal for d in base.decisions),
        "late_arrivals": None,
        "rendered": sum(d.quality is not None for d in base.decisions),
        "not_rebuilt": sum(d.skipped is not None for d in base.decisions),
        "max_abs_score_diff": max(diffs.values()) if diffs else None,
        "score_diffs": diffs,
        "counterfactual": [_summary(r, base) for r in [base, *others]] if score else [],
    }
    from services.recorder.replay import arrivals

    doc["late_arrivals"] = sum(arrivals(rec.sites[s]).late for s in doc["sites"]
                               if rec.sites[s].decisions)
    if json_out:
        print(json.dumps(doc, allow_nan=False, default=lambda x: None))
        return
    console.print(f"{recording}: {doc['decisions']} decisions ({', '.join(doc['sites'])}), "
                  f"policies {', '.join(doc['recorded_policies'])}")
    console.print(f"selections equal: {doc['selections_equal']}/{doc['decisions']} · AoI "
                  f"vectors equal: {doc['aoi_vectors_equal']} · late arrivals: "
                  f"{doc['late_arrivals']} · rebuilt renders: {doc['rendered']}")
    if diffs:
        console.print("max |replayed − recorded|: " + ", ".join(
            f"{k} {v:.2e}" for k, v in diffs.items()))
    if doc["counterfactual"]:
        from rich.table import Table

        table = Table(title="the same arrivals, paired by decision epoch (Δ: − recorded, "
                            "95% CI)")
        for col in ("policy", "n", "PSNR dB", "Δ PSNR", "SSIM", "Δ SSIM", "reward",
                    "cameras", "AoI used ms"):
            table.add_column(col)
        for row in doc["counterfactual"]:
            dp, ds = row["psnr_db_vs_recorded"], row["ssim_vs_recorded"]
            table.add_row(row["policy"], str(row["n"]), fmt(row["psnr_db"]),
                          fmt(dp["mean"], dp["ci95"]), fmt(row["ssim"], digits=3),
                          fmt(ds["mean"], ds["ci95"], digits=3), fmt(row["reward"], digits=3),
                          fmt(row["cameras_used"], digits=1),
                          fmt(row["aoi_selected_ms"], digits=0))
        console.print(table)
