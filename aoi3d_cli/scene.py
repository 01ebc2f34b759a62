"""``aoi3d scene …``: generate, inspect and export scene datasets (any supported layout)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from aoi3d.scene import (
    EXPORT_FORMATS,
    DatasetError,
    SceneConfig,
    ensure_dataset,
    export_dataset,
    generate_dataset,
    open_dataset,
)
from aoi3d.scene.framings import DEFAULT_FRAMING, FRAMING_DATASETS, FRAMING_SCENES
from aoi3d_cli.common import fail, make_console

app = typer.Typer(no_args_is_help=True, add_completion=False)
console = make_console()

_D = FRAMING_SCENES[DEFAULT_FRAMING]  # the defaults shown by --help
_DEFAULT_DATASET = Path(FRAMING_DATASETS[DEFAULT_FRAMING])


@app.callback()
def scene() -> None:
    """Generate and inspect the synthetic dynamic scene (a wind turbine)."""


def scene_config(framing: str, **options: Any) -> SceneConfig:
    """The scene ``aoi3d scene generate`` renders: the framing's
    (:data:`~aoi3d.scene.framings.FRAMING_SCENES`) with the given options (``None``: the
    framing's value). Bad values raise ``typer.BadParameter``."""
    if framing not in FRAMING_SCENES:
        raise typer.BadParameter(f"expected one of {', '.join(FRAMING_SCENES)}, got "
                                 f"{framing!r}", param_hint="'--framing'")
    try:
        return dataclasses.replace(FRAMING_SCENES[framing],
                                   **{k: v for k, v in options.items() if v is not None})
    except (TypeError, ValueError) as exc:
        raise typer.BadParameter(str(exc)) from exc


@app.command()
def generate(
    out: Annotated[Path | None, typer.Option(help=(
        "Dataset folder to write. Default: the framing's, "
        + ", ".join(f"{v} ({k})" for k, v in FRAMING_DATASETS.items()) + "."))] = None,
    width: Annotated[int, typer.Option(help="Image width in pixels.")] = _D.width,
    height: Annotated[int, typer.Option(help="Image height in pixels.")] = _D.height,
    fps: Annotated[int, typer.Option(help="Frames per second of every camera.")] = _D.fps,
    duration_s: Annotated[
        float, typer.Option(help="Length of the looped sequence, in seconds.")
    ] = _D.duration_s,
    rotor_rpm: Annotated[float | None, typer.Option(help=(
        "Rotor speed, revolutions/min. Default: the framing's, "
        + ", ".join(f"{c.rotor_rpm:g} ({k})" for k, c in FRAMING_SCENES.items()) + "."))]
    = None,
    spp: Annotated[int, typer.Option(help="Samples per pixel per axis (spp² per pixel).")] = (
        _D.spp
    ),
    seed: Annotated[int, typer.Option(help="Seed of the texture noise.")] = _D.seed,
    n_train: Annotated[int, typer.Option(help="Training cameras (camera 0 is held out).")] = (
        _D.n_train
    ),
    framing: Annotated[str, typer.Option(
        help="rotor: a close-up of the rotor from a 60° arc (the experiments' and the live "
             "pipeline's scene); site: the whole turbine from a 170° arc.")] = _D.framing,
    processes: Annotated[int, typer.Option(
        "--processes", "-j", "--workers",
        help="Rendering processes (--workers: the old name, kept for one release).")] = 1,
    force: Annotated[
        bool, typer.Option(help="Regenerate even when a dataset of this config is there.")
    ] = False,
) -> None:
    """Render every camera's frames and the transforms (cached by config hash)."""
    cfg = scene_config(framing, width=width, height=height, fps=fps, duration_s=duration_s,
                       n_train=n_train, rotor_rpm=rotor_rpm, spp=spp, seed=seed)
    out = out if out is not None else Path(FRAMING_DATASETS[framing])
    if processes < 1:
        raise typer.BadParameter(f"--processes must be ≥ 1, got {processes}")
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
                ds = generate_dataset(out, cfg, report, processes=processes)
            else:
                ds = ensure_dataset(out, cfg, report, processes=processes)
        except (FileExistsError, OSError) as exc:
            fail(exc)
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
    path: Annotated[Path, typer.Argument(help="Dataset folder (aoi3d, D-NeRF or DyNeRF).")] = (
        _DEFAULT_DATASET
    ),
    downscale: Annotated[
        float | None, typer.Option(help="D-NeRF/DyNeRF: read frames this many times smaller.")
    ] = None,
    width: Annotated[
        int | None, typer.Option(help="D-NeRF/DyNeRF: read frames at this width (pixels).")
    ] = None,
) -> None:
    """Print a dataset's layout, cameras, frames and box; check every frame file (present, not
    empty, a whole PNG) and decode one (videos are not decoded). Exits 1, naming the files,
    when any is missing or damaged."""
    try:
        ds = open_dataset(path, downscale=downscale, width=width)
    except (FileNotFoundError, ValueError, ImportError) as exc:
        fail(exc)
    aabb = np.asarray(ds.aabb)
    config = f"config {ds.config_hash}" if ds.config_hash else "not generated by aoi3d"
    console.print(f"[bold]{ds.root}[/]")
    console.print(f"{ds.layout} layout, {config}")
    console.print(
        f"{len(ds.cameras)} cameras (held-out {ds.heldout_id}, train {ds.train_ids[0]}.."
        f"{ds.train_ids[-1]}) × {ds.n_frames} frames at {ds.fps} fps = "
        f"{ds.duration_ms / 1000:g} s loop, {ds.width}×{ds.height} px"
    )
    console.print(f"aabb min {aabb[0].round(3).tolist()}  max {aabb[1].round(3).tolist()}")
    if ds.config:
        console.print(f"config {ds.config}")
    if ds.imported:
        console.print(f"imported from {ds.imported.get('source')} ({ds.imported.get('kind')}"
                      + (f", site {ds.imported['site']}" if ds.imported.get("site") else "")
                      + f"), from {ds.imported.get('t0_ms', 0):.0f} ms of its clock")
    table = Table(title="cameras (poses are OpenGL camera-to-world)")
    for col in ("id", "name", "role", "x", "y", "z", "distance", "fx", "look dir"):
        table.add_column(col, justify="right")
    for cam_id, cam in enumerate(ds.cameras):
        pos = cam.position
        look = -cam.c2w[:3, 2]
        role = ("held-out" if cam_id == ds.heldout_id
                else "train" if cam_id in ds.train_ids else "eval")
        table.add_row(
            str(cam_id),
            ds.camera_name(cam_id),
            role,
            f"{pos[0]:.2f}",
            f"{pos[1]:.2f}",
            f"{pos[2]:.2f}",
            f"{np.linalg.norm(pos):.2f}",
            f"{cam.fx:.1f}",
            "(" + ", ".join(f"{v:+.2f}" for v in look) + ")",
        )
    console.print(table)
    try:
        ds.require_frames()
    except DatasetError as err:
        fail(err)
    files = {ds.frame_relpath(c, k) for c in range(len(ds.cameras)) for k in range(ds.n_frames)}
    console.print(f"frames: all {len(files)} file(s) present and whole, one decoded")


@app.command()
def export(
    fmt: Annotated[
        str, typer.Option("--format", help=f"Layout to write: {' | '.join(EXPORT_FORMATS)}.")
    ],
    out: Annotated[Path, typer.Option(help="Folder to write (must be new or empty).")],
    dataset: Annotated[
        Path, typer.Option(help="Dataset to export, in any layout.")
    ] = _DEFAULT_DATASET,
    overwrite: Annotated[
        bool, typer.Option(help="Replace a dataset already at --out.")
    ] = False,
    crf: Annotated[
        int, typer.Option(help="DyNeRF: x264 quality, 0 (lossless) … 51 (worst).")
    ] = 15,
    downscale: Annotated[
        float | None, typer.Option(help="D-NeRF/DyNeRF source: read it this many times "
                                        "smaller (converts a full-size dataset once).")
    ] = None,
    width: Annotated[
        int | None, typer.Option(help="D-NeRF/DyNeRF source: read it at this width.")
    ] = None,
) -> None:
    """Write a dataset as DyNeRF videos (camNN.mp4 + poses_bounds.npy) or D-NeRF JSON."""
    if fmt not in EXPORT_FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(EXPORT_FORMATS)}, "
                                 f"got {fmt!r}")
    try:
        ds = open_dataset(dataset, downscale=downscale, width=width)
    except (FileNotFoundError, ValueError, ImportError) as exc:
        fail(exc)
    options: dict[str, object] = {"overwrite": overwrite}
    if fmt == "dynerf":
        options["crf"] = crf
    started = time.perf_counter()
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("frames"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(f"exporting {fmt}", total=None)
        options["progress"] = lambda done, total: bar.update(task, completed=done, total=total)
        try:
            written = export_dataset(ds, out, fmt, **options)
        except (FileExistsError, OSError, ValueError, ImportError) as exc:
            fail(exc)
    console.print(
        f"wrote {fmt} ({len(ds.cameras)} cameras × {ds.n_frames} frames, "
        f"{ds.width}×{ds.height}) to {written} in {time.perf_counter() - started:.1f} s"
    )


@app.command("import")
def import_(
    recording: Annotated[Path, typer.Argument(help=(
        "An MCAP file: an aoi3d recording (`aoi3d up --record`) or a rosbag2 of real "
        "cameras (`ros2 bag record -s mcap`: its folder or its .mcap file)."))],
    out: Annotated[Path, typer.Option(help="Dataset folder to write.")],
    site: Annotated[str | None, typer.Option(
        help="The recording's site to import (needed when it holds several).")] = None,
    rig: Annotated[Path | None, typer.Option(
        help="A rosbag2's rig file (the one `aoi3d up --rig` runs it with): which topic is "
             "which camera, which is the truth.")] = None,
    fps: Annotated[int | None, typer.Option(
        min=1, max=1000, help="Frames per second of the dataset's grid (default: the truth "
                              "camera's rate, rounded); the grid may hold 2,000,000 frames "
                              "(frames × cameras) at most.")] = None,
    aabb: Annotated[str | None, typer.Option(
        help="Scene box 'xmin,ymin,zmin,xmax,ymax,zmax' (default: the recording's renders' "
             "box, or the rig file's).")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace a dataset already at --out.")]
    = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")]
    = False,
) -> None:
    """Import a recording as a dataset for the experiments: a fixed rig (camera 0 the truth
    camera) on a frame grid, each frame the newest the camera had generated by then. The
    report counts per camera the frames used, dropped between grid points and held over a
    gap (docs/recording.md)."""
    import json

    from services.recorder.importer import NotImportable, import_mcap

    box = None
    if aabb is not None:
        try:
            box = [float(v) for v in aabb.split(",")]
        except ValueError:
            box = []
        if len(box) != 6:
            raise typer.BadParameter("six numbers: xmin,ymin,zmin,xmax,ymax,zmax",
                                     param_hint="'--aabb'")
    if out.exists() and not out.is_dir():
        fail(f"{out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        fail(f"{out} exists and is not empty; --overwrite replaces a dataset there")
    started = time.perf_counter()
    try:
        ds, report = import_mcap(recording, out, site=site, rig=rig, fps=fps, aabb=box)
    except (NotImportable, FileExistsError, OSError, ValueError) as err:
        fail(err)
    if json_out:
        print(json.dumps(report.to_dict()))
        return
    console.print(f"wrote {ds.root}: {len(ds.cameras)} cameras × {ds.n_frames} frames at "
                  f"{ds.fps} fps, {ds.width}×{ds.height} px, from {report.kind} {recording} "
                  f"in {time.perf_counter() - started:.1f} s")
    table = Table(title="cameras (0: the truth camera)")
    for col in ("id", "name", "recorded id", "frames", "used", "dropped", "held"):
        table.add_column(col, justify="right")
    for row in report.cameras:
        table.add_row(*(str(row[k]) for k in ("id", "name", "recorded_id", "frames", "used",
                                               "dropped", "held")))
    console.print(table)
    held = sum(r["held"] for r in report.cameras[1:])
    grid = report.n_frames * (len(report.cameras) - 1)
    if report.kind == "recording" and grid and held / grid > 0.1:
        console.print(f"[yellow]{100 * held / grid:.0f} % of the training cameras' grid frames "
                      "repeat an older frame: a recording keeps the frames that reached the "
                      "edge, and its link lost the rest. The experiments run their own channel "
                      "on these frames; for a dataset of every frame the cameras made, record "
                      "them where they are made (a rosbag2 at the robot) or on a lossless "
                      "link.[/]")
    if report.rejected:
        console.print("refused by the ingest (cut_short: a file read up to a cut): " + ", ".join(
            f"{k} {v}" for k, v in sorted(report.rejected.items())))
