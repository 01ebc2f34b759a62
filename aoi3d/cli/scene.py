"""``aoi3d scene …``: generate and inspect the synthetic dynamic scene dataset."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from aoi3d.scene import SceneConfig, ensure_dataset, generate_dataset, load_dataset

app = typer.Typer(no_args_is_help=True, add_completion=False)
console = Console()

_D = SceneConfig()  # the defaults shown by --help


@app.callback()
def scene() -> None:
    """Generate and inspect the synthetic dynamic scene (a wind turbine)."""


@app.command()
def generate(
    out: Annotated[Path, typer.Option(help="Dataset folder to write.")] = Path("data/turbine"),
    width: Annotated[int, typer.Option(help="Image width in pixels.")] = _D.width,
    height: Annotated[int, typer.Option(help="Image height in pixels.")] = _D.height,
    fps: Annotated[int, typer.Option(help="Frames per second of every camera.")] = _D.fps,
    duration_s: Annotated[
        float, typer.Option(help="Length of the looped sequence, in seconds.")
    ] = _D.duration_s,
    rotor_rpm: Annotated[float, typer.Option(help="Rotor speed, revolutions/min.")] = (
        _D.rotor_rpm
    ),
    spp: Annotated[int, typer.Option(help="Samples per pixel per axis (spp² per pixel).")] = (
        _D.spp
    ),
    seed: Annotated[int, typer.Option(help="Seed of the texture noise.")] = _D.seed,
    n_train: Annotated[int, typer.Option(help="Training cameras (camera 0 is held out).")] = (
        _D.n_train
    ),
    workers: Annotated[int, typer.Option(help="Rendering processes.")] = 1,
    force: Annotated[
        bool, typer.Option(help="Regenerate even when a dataset of this config is there.")
    ] = False,
) -> None:
    """Render every camera's frames and the transforms (cached by config hash)."""
    try:
        cfg = SceneConfig(
            width=width,
            height=height,
            fps=fps,
            duration_s=duration_s,
            n_train=n_train,
            rotor_rpm=rotor_rpm,
            spp=spp,
            seed=seed,
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    if workers < 1:
        raise typer.BadParameter(f"--workers must be ≥ 1, got {workers}")
    started = time.perf_counter()
    generated = False
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("frames"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(f"rendering {out}", total=None)

        def report(done: int, total: int) -> None:
            nonlocal generated
            generated = True
            bar.update(task, completed=done, total=total)

        try:
            if force:
                ds = generate_dataset(out, cfg, report, workers=workers)
            else:
                ds = ensure_dataset(out, cfg, report, workers=workers)
        except (FileExistsError, OSError) as exc:
            console.print(f"[red]error:[/] {exc}")
            raise typer.Exit(1) from exc
    elapsed_s = time.perf_counter() - started
    n = len(ds.cameras) * ds.n_frames
    what = f"{len(ds.cameras)} cameras × {ds.n_frames} frames, {ds.width}×{ds.height}"
    if generated:
        console.print(f"wrote {n} frames ({what}) to {ds.root} in {elapsed_s:.1f} s")
    else:
        console.print(
            f"up to date: {ds.root} ({what}, config {ds.config_hash}); "
            "nothing to do (--force regenerates)"
        )


@app.command()
def info(
    path: Annotated[Path, typer.Argument(help="Dataset folder.")] = Path("data/turbine"),
) -> None:
    """Print a dataset's cameras, frames and box."""
    try:
        ds = load_dataset(path)
    except (FileNotFoundError, ValueError) as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(1) from exc
    aabb = np.asarray(ds.aabb)
    console.print(f"[bold]{ds.root}[/]  (config {ds.config_hash})")
    console.print(
        f"{len(ds.cameras)} cameras (held-out {ds.heldout_id}, train {ds.train_ids[0]}.."
        f"{ds.train_ids[-1]}) × {ds.n_frames} frames at {ds.fps} fps = "
        f"{ds.duration_ms / 1000:g} s loop, {ds.width}×{ds.height} px"
    )
    console.print(f"aabb min {aabb[0].round(3).tolist()}  max {aabb[1].round(3).tolist()}")
    console.print(f"config {ds.config}")
    missing = ds.missing_frames()
    if missing:
        console.print(f"[yellow]{missing} frame files are missing[/]")
    table = Table(title="cameras (world z-up; poses are OpenGL camera-to-world)")
    for col in ("id", "role", "x", "y", "z", "distance", "fx", "look dir"):
        table.add_column(col, justify="right")
    for cam_id, cam in enumerate(ds.cameras):
        pos = cam.position
        look = -cam.c2w[:3, 2]
        table.add_row(
            str(cam_id),
            "held-out" if cam_id == ds.heldout_id else "train",
            f"{pos[0]:.2f}",
            f"{pos[1]:.2f}",
            f"{pos[2]:.2f}",
            f"{np.linalg.norm(pos):.2f}",
            f"{cam.fx:.1f}",
            "(" + ", ".join(f"{v:+.2f}" for v in look) + ")",
        )
    console.print(table)
