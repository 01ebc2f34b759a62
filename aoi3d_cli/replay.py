"""``aoi3d replay``: re-run a recording (``aoi3d up --record``) on the virtual clock.

Under the recorded policy it checks that the recording reproduces: every decision's
selection, and every scored render's PSNR, SSIM, LPIPS and reward, rebuilt with the live
worker's and metrics service's own code (:mod:`services.recorder.replay`; a ``stream`` render,
the live default, through its worker's chain of jobs: :mod:`services.recorder.chains`). With
``--policy`` it also gives each other policy's counterfactual on the same arrivals, paired by
decision epoch with the recorded policy's replayed scores (docs/recording.md).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from aoi3d_cli.common import fail, fmt, make_console, stop_on_signal

if TYPE_CHECKING:
    from rich.console import Console

    from services.recorder.recording import Recorded
    from services.recorder.replay import ReplayResult


def _scored_total(rec, sites) -> int:
    """The decisions the live pool rendered and scored, over ``sites`` (None: all)."""
    return sum(1 for name, srec in rec.sites.items() if sites is None or name in sites
               for d in srec.decisions
               if (k := (d.incarnation, d.decision_id)) in srec.renders and k in srec.qualities)


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
        min=0, help="Rebuild at most this many scored decisions per site, the first that "
                    "every policy asked for can rebuild (default: all; each is one "
                    "reconstruction, about half a second on one core).")] = None,
    score: Annotated[bool, typer.Option(
        help="Rebuild and score the renders (--no-score: compare the selections only).")]
    = True,
    threads: Annotated[int | None, typer.Option(
        min=1, help="Torch threads of the reconstruction (default: the recorded workers').")]
    = None,
    live: Annotated[bool, typer.Option(
        "--live", help="Play the recording into a running pipeline as its cameras (ROS 2 "
                       "on Zenoh, for `aoi3d up --rig`; --write-rig writes its rig file) "
                       "instead of re-running it on the virtual clock.")] = False,
    connect: Annotated[str, typer.Option(
        help="--live: Zenoh endpoint(s) to connect to, comma-separated.")]
    = "tcp/127.0.0.1:7447",
    time_scale: Annotated[float, typer.Option(
        help="--live: scene seconds per wall second (give `aoi3d up --rig` the same; the rig "
             "file says it).")] = 1.0,
    epoch_s: Annotated[float | None, typer.Option(
        help="--live: the pipeline's epoch (Unix s, the ingest's GET /status time.epoch_s): "
             "keep the recording's phase on its decision grid.")] = None,
    key_format: Annotated[str, typer.Option(
        "--format", help="--live: rmw_zenoh or bridge keys.")] = "rmw_zenoh",
    domain_id: Annotated[int, typer.Option(min=0, max=232, help="--live: ROS_DOMAIN_ID.")] = 0,
    namespace: Annotated[str, typer.Option(help="--live: the bridge's namespace.")] = "",
    write_rig: Annotated[Path | None, typer.Option(
        help="--live: write the rig file that reads what is played.")] = None,
    rig_only: Annotated[bool, typer.Option(
        help="--live: write the rig file (--write-rig) and exit.")] = False,
) -> None:
    """Re-run a recording on the virtual clock with its recorded frames, generation and
    arrival times: under the recorded policy it must reproduce every selection and every
    score; under --policy P the counterfactual on the same arrivals, paired by epoch.
    With --live, play its frames into a running pipeline as its cameras instead."""
    if live:
        if policy or json_out or max_renders is not None or not score or threads:
            raise typer.BadParameter("--live plays the recording's frames; --policy, --json, "
                                     "--max-renders, --no-score and --threads are for the "
                                     "virtual clock", param_hint="'--live'")
        if len(site or []) > 1:
            raise typer.BadParameter("--live plays one site", param_hint="'--site'")
        _live(recording, site[0] if site else None, connect, time_scale, epoch_s, key_format,
              domain_id, namespace, write_rig, rig_only)
        return
    if write_rig is not None or rig_only or epoch_s is not None:
        raise typer.BadParameter("--write-rig, --rig-only and --epoch-s are for --live",
                                 param_hint="'--live'")
    _virtual(recording, policy, json_out, site, max_renders, score, threads)


def _virtual(recording: Path, policy: list[str] | None, json_out: bool, site: list[str] | None,
             max_renders: int | None, score: bool, threads: int | None) -> None:
    """``aoi3d replay`` on the virtual clock: the recorded policy, then each --policy on the
    same arrivals."""
    from services.recorder.replay import rebuildable_keys, score_diffs
    from services.recorder.replay import replay as run_replay

    console = make_console(stderr=json_out)
    specs = _policies(policy)
    from aoi3d.policy import PolicySpecError

    rec = _load(recording, site)
    scorers: dict = {}
    kwargs: dict[str, Any] = dict(sites=site, score=score, max_renders=max_renders,
                                  threads=threads, scorers=scorers)
    try:
        # with counterfactuals, every policy rebuilds the same epochs: those all of them can
        paired = rebuildable_keys(rec, [None, *specs], sites=site) if specs and score else None
        base = run_replay(rec, None, only=paired, **kwargs)
        others = [run_replay(rec, spec, only=paired, **kwargs) for spec in specs]
    except (ValueError, PolicySpecError) as err:
        fail(err)
    diffs = score_diffs(rec, base)
    doc = _document(recording, rec, site, base, others, paired, diffs, score)
    doc["score_diffs_not_exact"] = score_diffs(rec, base, exact=False)
    doc["chains"] = {r.policy: r.chains.to_dict() for r in [base, *others]} if score else {}
    if json_out:
        print(json.dumps(doc, allow_nan=False, default=lambda x: None))
        return
    _print_report(console, recording, doc, diffs)


def _policies(policy: list[str] | None) -> list[str]:
    """--policy's specs (repeated or comma lists), each checked."""
    specs = [s.strip() for p in (policy or []) for s in p.split(",") if s.strip()]
    from aoi3d.policy import PolicySpecError, parse_policy

    for spec in specs:
        try:
            parse_policy(spec)
        except PolicySpecError as err:
            raise typer.BadParameter(str(err), param_hint="'--policy'") from None
    return specs


def _load(recording: Path, site: list[str] | None) -> Recorded:
    """The recording, holding every site of --site; else one line and exit status 1."""
    from services.recorder.recording import McapFileError, load

    try:
        rec = load(recording)
    except (FileNotFoundError, OSError) as err:
        fail(err)
    except McapFileError as err:  # not MCAP, a record over the caps, a corrupt chunk
        fail(f"{recording} cannot be read as an MCAP recording: {err}")
    if not any(s.decisions for s in rec.sites.values()):
        fail(f"{recording} holds no decision to replay"
             + (f" ({rec.cut_short[0]})" if rec.cut_short else ""))
    for note in rec.cut_short:  # read up to the cut: say so, on stderr
        typer.echo(f"note: {note}", err=True)
    if rec.refused:
        typer.echo("note: messages not read: " + ", ".join(
            f"{k} {v}" for k, v in sorted(rec.refused.items())), err=True)
    missing = [s for s in (site or []) if s not in rec.sites]
    if missing:
        fail(f"no site {', '.join(missing)} in the recording; it holds "
             f"{', '.join(sorted(rec.sites)) or 'none'}")
    return rec


def _document(recording: Path, rec: Recorded, site: list[str] | None, base: ReplayResult,
              others: list[ReplayResult], paired: set[tuple[str, tuple[int, int]]] | None,
              diffs: dict[str, float], score: bool) -> dict[str, Any]:
    """What ``--json`` prints (and the tables show)."""
    from services.recorder.replay import Counterfactual

    doc: dict[str, Any] = {
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
        "not_exact": sum(d.exact is False for d in base.decisions),
        "not_rebuilt": (sum(d.skipped is not None for d in base.decisions) if paired is None
                        else _scored_total(rec, site) - len(paired)),
        "paired_epochs": None if paired is None else len(paired),
        "max_abs_score_diff": max(diffs.values()) if diffs else None,
        "score_diffs": diffs,
        "counterfactual": ([Counterfactual.of(r, base).to_dict() for r in [base, *others]]
                           if score else []),
    }
    from services.recorder.arrivals import arrivals

    doc["late_arrivals"] = sum(arrivals(rec.sites[s]).late for s in doc["sites"]
                               if rec.sites[s].decisions)
    return doc


def _print_report(console: Console, recording: Path, doc: dict[str, Any],
                  diffs: dict[str, float]) -> None:
    """The report as text: what was replayed, how it agrees, the counterfactual table."""
    console.print(f"{recording}: {doc['decisions']} decisions ({', '.join(doc['sites'])}), "
                  f"policies {', '.join(doc['recorded_policies'])}")
    console.print(f"selections equal: {doc['selections_equal']}/{doc['decisions']} · AoI "
                  f"vectors equal: {doc['aoi_vectors_equal']} · late arrivals: "
                  f"{doc['late_arrivals']} · rebuilt renders: {doc['rendered']}")
    if diffs:
        console.print("max |replayed − recorded|: " + ", ".join(
            f"{k} {v:.2e}" for k, v in diffs.items()))
    if doc["not_exact"]:
        chains = doc["chains"]["recorded"]
        console.print(f"not reproducible exactly: {doc['not_exact']} stream renders after "
                      f"{chains['gaps']} gaps and {chains['skipped']} skipped jobs in their "
                      f"workers' chains (before the next cold start); max |replayed − "
                      f"recorded| of them: " + ", ".join(
                          f"{k} {v:.2e}" for k, v in doc["score_diffs_not_exact"].items()))
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


def _live(recording: Path, site: str | None, connect: str, time_scale: float,
          epoch_s: float | None, key_format: str, domain_id: int, namespace: str,
          write_rig: Path | None, rig_only: bool) -> None:
    """``aoi3d replay --live``: the recording's frames as ROS 2 cameras on Zenoh."""
    import time

    from aoi3d_cli.ros2 import write_rig_file
    from services.recorder.importer import recorded_streams
    from services.recorder.player import PlayConfig, Player, rig_document
    from services.ros.publishing import zenoh_publishing

    try:
        cfg = PlayConfig(format=key_format, domain_id=domain_id, namespace=namespace,
                         time_scale=time_scale, epoch_s=epoch_s)
        site_name, streams, box = recorded_streams(recording, site)
    except (FileNotFoundError, OSError, ValueError) as err:
        fail(err)
    frames = {n: s.frames for n, s in streams.items()}
    if not frames or set(frames) == {0}:
        fail(f"{recording}: site {site_name} holds no camera frame with pixels to play")
    if box is None:
        fail(f"{recording}: no render records the scene box the rig file needs")
    if write_rig is not None:
        write_rig_file(write_rig, rig_document(frames, cfg, box))
        typer.echo(f"rig file: {write_rig} (aoi3d up --rig {write_rig})")
    if rig_only:
        if write_rig is None:
            raise typer.BadParameter("needs --write-rig", param_hint="'--rig-only'")
        return
    player = Player(frames, cfg, lambda *sample: put(*sample),
                    pixels=lambda n, fr: streams[n].pixels(fr))
    span = (player.order[-1][0] - player.order[0][0]) / 1000.0
    typer.echo(f"playing {len(player.order)} frames of {len(frames)} cameras ({site_name}, "
               f"{span:.1f} scene s) at time scale {time_scale:g} via {connect}")
    t0 = time.monotonic()
    endpoints = [c.strip() for c in connect.split(",") if c.strip()]
    with zenoh_publishing(endpoints, player.keys(), tokens=player.tokens) as put, \
            stop_on_signal() as stop:
        player.run(stop)
    typer.echo(f"played {player.sent} frames in {time.monotonic() - t0:.1f} s"
               + (f" (shifted {player.shift_ms:g} ms onto the pipeline's clock)"
                  if epoch_s is not None else ""))
