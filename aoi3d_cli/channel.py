"""``aoi3d channel …``: simulate the cameras' D/G/1/0 uplinks and compare with the theory.

Cameras are numbered 1..N as in the pipeline (camera 0, the held-out view, has no uplink).
The channel package (scipy) is imported inside the command.
"""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Annotated, Any

import typer

from aoi3d_cli.common import fmt, make_console

if TYPE_CHECKING:
    from rich.console import Console

app = typer.Typer(no_args_is_help=True, add_completion=False)


@app.callback()
def channel() -> None:
    """Simulate the cameras' D/G/1/0 uplinks and their AoI."""


def _table(result: dict[str, Any], console: Console) -> None:
    from rich.table import Table

    cfg = result["config"]
    theory = result["theory"]
    table = Table(
        title=(
            f"{cfg['n_cameras']} links, delay {cfg['delay']}, period {cfg['period_ms']} ms, "
            f"{cfg['duration_s']:g} s, seed {cfg['seed']} (AoI in ms)"
        )
    )
    for name in ("camera", "mean AoI", "p50", "p99", "drop", "deliv/s", "offered", "dropped",
                 "delivered"):
        table.add_column(name, justify="right")

    def row(label: str, s: dict[str, Any], style: str | None = None) -> None:
        table.add_row(
            label,
            fmt(s.get("mean_aoi_ms")),
            fmt(s.get("p50_aoi_ms"), digits=0),
            fmt(s.get("p99_aoi_ms"), digits=0),
            fmt(s.get("drop_ratio"), digits=4),
            fmt(s.get("delivered_per_s")),
            fmt(s.get("offered")),
            fmt(s.get("dropped")),
            fmt(s.get("delivered")),
            style=style,
        )

    for cam in result["per_camera"]:
        row(str(cam["camera"]), cam)
    table.add_section()
    row("all", result, style="bold")
    row("theory", theory, style="cyan")
    console.print(table)


def simulate_cmd(
    delay: Annotated[
        str, typer.Option(help="Delay spec: exp:MEAN, const:D, uniform:LO:HI, gamma:K:THETA, "
                          "lognormal:MU:SIGMA (ms); or a channel that changes: "
                          "regimes:SPEC@DUR,… (cycling, e.g. regimes:exp:20@10s,exp:200@10s), "
                          "burst:GOOD,BAD[,good=DUR][,bad=DUR] (Gilbert–Elliott), "
                          "trace:PATH[,offset=MS][,spread=MS][,scale=S] (a mahimahi uplink "
                          "trace per camera), cell:PATH[,…] (the cameras share one trace's "
                          "capacity).")
    ] = "exp:60",
    period_ms: Annotated[int, typer.Option(min=1, help="Frame period C (ms).")] = 30,
    cameras: Annotated[int, typer.Option(min=1, help="Cameras (one link each).")] = 18,
    duration_s: Annotated[float, typer.Option(min=0.001, help="Simulated time (s).")] = 600.0,
    seed: Annotated[int, typer.Option(help="Seed of the per-camera random streams.")] = 1,
    phase_ms: Annotated[int, typer.Option(min=0, help="First generation slot (ms).")] = 0,
    frame_bytes: Annotated[int, typer.Option(min=1, help="Every frame's encoded size in bytes "
                                             "(a trace or cell channel's transmission time "
                                             "depends on it).")] = 12_000,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Simulate the links and print AoI and drop statistics next to the exact theory.

    Cameras are numbered 1..N, as in the pipeline (``per_camera[i]["camera"]`` in the JSON)."""

    import numpy as np

    from aoi3d.channel import (
        DelaySpecError,
        channel_statistics,
        channel_theory,
        parse_channel,
        simulate,
    )

    try:
        channel = parse_channel(delay)
    except DelaySpecError as err:
        raise typer.BadParameter(str(err), param_hint="'--delay'") from None
    duration_ms = round(duration_s * 1000.0)
    started = time.perf_counter()
    run = simulate(channel, period_ms, cameras, duration_ms, seed, phase_ms=phase_ms,
                   frame_bytes=frame_bytes)
    stats = channel_statistics(run)
    transmission = (np.concatenate([d - g for g, d in zip(run.gen_ms, run.delivery_ms,
                                                           strict=True)])
                    if run.n_cameras else np.zeros(0))
    stats["mean_transmission_ms"] = float(transmission.mean()) if transmission.size else None
    stats["per_camera"] = [{"camera": entry["link"] + 1,
                            **{k: v for k, v in entry.items() if k != "link"}}
                           for entry in stats["per_camera"]]  # links 0..N-1 → cameras 1..N
    elapsed_s = time.perf_counter() - started
    dist = channel.stationary
    try:
        theory: dict[str, Any] = (
            channel_theory(dist, period_ms).to_dict() if dist is not None else
            {"error": "no closed-form theory for a channel that changes"})
    except ValueError as err:  # e.g. a tail too heavy for the numeric theory
        theory = {"error": str(err)}
    config = {
        "delay": channel.spec,
        "period_ms": period_ms,
        "n_cameras": cameras,
        "duration_s": duration_ms / 1000.0,
        "duration_ms": duration_ms,
        "seed": seed,
        "phase_ms": phase_ms,
        "frame_bytes": frame_bytes,
    }
    result = {"config": config, **stats, "theory": theory}
    if as_json:
        typer.echo(json.dumps(result))
        return
    console = make_console()
    _table(result, console)
    camera_slots = cameras * duration_ms
    console.print(
        f"simulated {camera_slots:,} camera-slots in {elapsed_s * 1000:.1f} ms "
        f"({camera_slots / max(elapsed_s, 1e-9) / 1e6:.0f} M/s)"
    )


app.command("simulate")(simulate_cmd)
