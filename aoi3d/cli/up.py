"""``aoi3d up``: the whole live pipeline on this machine."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

console = Console()


def up(
    dataset: Annotated[Path, typer.Option(help="Scene dataset folder (generated if missing).")]
    = Path("data/turbine"),
    time_scale: Annotated[float, typer.Option(
        help="Simulation seconds per wall second; < 1 slows the world so the CPU trainer "
             "keeps pace.")] = 0.1,
    run_id: Annotated[str, typer.Option(help="Run id: the <run> in every key expression.")]
    = "default",
    zenoh_port: Annotated[int, typer.Option(help="TCP port of the local Zenoh router.")] = 7447,
    port_offset: Annotated[int, typer.Option(
        help="Added to the default REST ports 8101..8105.")] = 0,
    log_dir: Annotated[Path, typer.Option(help="Where each process's log goes.")]
    = Path("runs/logs"),
    duration_s: Annotated[float | None, typer.Option(
        help="Stop after this many seconds (default: run until Ctrl-C).")] = None,
    quiet: Annotated[bool, typer.Option(
        help="Do not echo the services' logs to the console.")] = False,
) -> None:
    """Run the Zenoh router and the five services locally, supervised, until Ctrl-C."""
    from services.supervisor import SERVICES, Supervisor, UpConfig

    logging.basicConfig(level=logging.INFO, format="%(asctime)s up %(levelname)s: %(message)s")
    _ensure_scene(dataset)
    cfg = UpConfig(dataset=dataset, run_id=run_id, time_scale=time_scale,
                   zenoh_port=zenoh_port, port_offset=port_offset, log_dir=log_dir,
                   duration_s=duration_s, echo=not quiet)

    def show_where(sup: Supervisor) -> None:
        table = Table(title=f"aoi3d pipeline up (run '{run_id}', time scale {time_scale})")
        for col in ("service", "REST API (docs at /docs)", "try"):
            table.add_column(col, no_wrap=True)
        hints = {
            "camera": "GET /config",
            "network": "GET /channel",
            "scheduler": "GET /aoi, PUT /policy",
            "trainer": "GET /status, /render.png",
            "metrics": "GET /quality?limit=5",
        }
        for name in SERVICES:
            table.add_row(name, f"http://127.0.0.1:{cfg.port(name)}", hints[name])
        table.add_row("router", f"tcp/127.0.0.1:{zenoh_port}", "Zenoh, multicast off")
        console.print(table)
        sched = f"http://127.0.0.1:{cfg.port('scheduler')}/policy"
        console.print(f"Change MAT: curl -X PUT {sched} -H 'content-type: application/json' "
                      """-d '{"kind":"mat","mat_ms":20}'""", soft_wrap=True)
        console.print(f"Logs: {log_dir}/<service>.log · Prometheus metrics: <service>/metrics "
                      "· stop with Ctrl-C", soft_wrap=True)

    code = Supervisor(cfg, on_ready=show_where).run()
    raise typer.Exit(code)


def _ensure_scene(dataset: Path) -> None:
    """Use the dataset at ``dataset`` if there is one (any layout ``open_dataset`` reads);
    else generate the default synthetic scene there."""
    import time

    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from aoi3d.scene import SceneConfig, detect_layout, ensure_dataset, open_dataset

    try:
        layout = detect_layout(dataset)
    except FileNotFoundError:
        layout = None
    if layout is not None:
        ds = open_dataset(dataset)
        console.print(f"scene: {dataset} ({layout} layout, {len(ds.cameras)} cameras × "
                      f"{ds.n_frames} frames, {ds.width}×{ds.height})")
        return

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/"
                  "{task.total}"), TimeRemainingColumn(), console=console,
                  transient=True) as progress:
        task = None

        def report(done: int, total: int) -> None:
            nonlocal task
            if task is None:
                task = progress.add_task(f"generating the scene into {dataset}", total=total)
            progress.update(task, completed=done)

        t0 = time.perf_counter()
        ds = ensure_dataset(dataset, SceneConfig(), progress=report)
    made = f", generated in {time.perf_counter() - t0:.1f} s" if task is not None else ""
    console.print(f"scene: {dataset} ({len(ds.cameras)} cameras × {ds.n_frames} frames, "
                  f"{ds.width}×{ds.height}{made})")
