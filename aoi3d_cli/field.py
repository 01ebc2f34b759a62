"""``aoi3d field …``: list the radiance-field backends, train one on a dataset instant.

Torch and the field package are imported inside the commands, so that other ``aoi3d``
commands start without them.
"""

from __future__ import annotations

import inspect
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from aoi3d.scene import SceneDataset, open_dataset, to_uint8
from aoi3d.scene.framings import DEFAULT_FRAMING, FRAMING_DATASETS
from aoi3d_cli.common import fail, make_console

if TYPE_CHECKING:
    from aoi3d.field import FieldConfig, FieldTrainer
    from aoi3d.quality import LpipsFn
    from aoi3d.scene import Camera

app = typer.Typer(no_args_is_help=True, add_completion=False)
console = make_console()


@app.callback()
def field() -> None:
    """Radiance-field backends: list them, train one on one instant of a dataset."""


def backend_summary(cls: type[FieldConfig]) -> str:
    """The first paragraph of the config's docstring, on one line."""
    doc = inspect.getdoc(cls) or ""
    if not doc or doc.startswith(f"{cls.__name__}("):  # dataclass's generated signature
        return "(no description)"
    return " ".join(doc.split("\n\n")[0].split())


def parse_cameras(spec: str, ds: SceneDataset) -> list[int]:
    """``"1-18"``, ``"1,4,8"``, ``"1-6,10"`` → camera ids (in order, without repeats).

    Raises ``ValueError`` for malformed ranges, unknown ids and the held-out camera.
    """
    ids: list[int] = []
    for part in (p.strip() for p in spec.split(",")):
        if not part:
            continue
        lo, sep, hi = part.partition("-")
        try:
            first, last = int(lo), int(hi) if sep else int(lo)
        except ValueError:
            raise ValueError(f"bad camera range {part!r}: use e.g. 1-18 or 1,4,8") from None
        if last < first:
            raise ValueError(f"bad camera range {part!r}: the end is before the start")
        ids.extend(i for i in range(first, last + 1) if i not in ids)
    if not ids:
        raise ValueError(f"no cameras in {spec!r}")
    n = len(ds.cameras)
    unknown = [i for i in ids if not 0 <= i < n]
    if unknown:
        raise ValueError(f"cameras {unknown} do not exist: the dataset has ids 0..{n - 1}")
    if ds.heldout_id in ids:
        raise ValueError(f"camera {ds.heldout_id} is the held-out novel view; train on others")
    return ids


def _lpips(image: np.ndarray, truth: np.ndarray, fn: LpipsFn | None) -> tuple[float | None, str]:
    if fn is None:
        return None, "weights not cached (python -m aoi3d.lpips fetch)"
    try:
        return float(fn(image, truth.astype(np.float32) / 255.0)), ""
    except ValueError as err:  # e.g. an image smaller than AlexNet needs
        return None, str(err)


@app.command()
def backends() -> None:
    """List the registered backends (``--backend`` names), one line each."""
    from aoi3d.field import BACKENDS

    table = Table(title="radiance-field backends (aoi3d.field.BACKENDS)")
    table.add_column("name", style="bold")
    table.add_column("config")
    table.add_column("description")
    for name, cls in BACKENDS.items():
        table.add_row(name, cls.__name__, backend_summary(cls))
    console.print(table)


def _checked(backend: str, seconds: float, every: float, threads: int | None,
             device: str) -> str:
    """The options that need no dataset, checked (a bad one is a usage error naming it); the
    torch device --device stands for."""
    from aoi3d.device import resolve_device
    from aoi3d.field import UnknownBackendError, check_backend

    try:
        check_backend(backend)
    except UnknownBackendError as err:
        raise typer.BadParameter(str(err), param_hint="--backend") from None
    if not (math.isfinite(seconds) and seconds > 0):
        raise typer.BadParameter(f"must be > 0, got {seconds}", param_hint="--seconds")
    if not (math.isfinite(every) and every > 0):
        raise typer.BadParameter(f"must be > 0, got {every}", param_hint="--every")
    if threads is not None and threads < 1:
        raise typer.BadParameter(f"must be >= 1, got {threads}", param_hint="--threads")
    try:
        return resolve_device(device)
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="--device") from None


def _train_scoring(trainer: FieldTrainer, camera: Camera, truth: np.ndarray,
                   lpips_fn: LpipsFn | None, seconds: float, every: float
                   ) -> tuple[np.ndarray, float, str]:
    """Train for ``seconds`` of training time, rendering and scoring the novel view every
    ``every`` s and at the end (a line each): the last render, the training time, and why
    LPIPS is missing ("" when it is not)."""
    from aoi3d.quality import psnr, ssim

    train_s = 0.0
    next_score_s = min(every, seconds)
    image = truth
    lpips_note = ""
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                  TextColumn("{task.completed:.1f}/{task.total:g} s"),
                  TextColumn("{task.fields[info]}"), TimeElapsedColumn(),
                  console=console) as bar:
        task = bar.add_task("training", total=seconds, info="")
        while True:
            t0 = time.perf_counter()
            loss = trainer.step(1)
            train_s += time.perf_counter() - t0
            bar.update(task, completed=min(train_s, seconds),
                       info=f"step {trainer.steps}, loss {loss:.4f}")
            if train_s < next_score_s:
                continue
            r0 = time.perf_counter()
            image = trainer.render(camera)
            render_s = time.perf_counter() - r0
            lp, note = _lpips(image, truth, lpips_fn)
            lpips_note = lpips_note or note
            bar.console.print(
                f"{train_s:6.1f} s  step {trainer.steps:6d}  PSNR {psnr(image, truth):6.2f} dB  "
                f"SSIM {ssim(image, truth):.4f}  LPIPS "
                f"{'—' if lp is None else f'{lp:.4f}'}  render {render_s * 1000:.0f} ms")
            if train_s >= seconds:
                break
            while next_score_s <= train_s:
                next_score_s += every
            next_score_s = min(next_score_s, seconds)
    return image, train_s, lpips_note


@app.command()
def train(
    backend: Annotated[str, typer.Option(help="Backend name (see `aoi3d field backends`).")] = (
        "grid"
    ),
    dataset: Annotated[Path, typer.Option(help="Dataset folder (aoi3d, D-NeRF or DyNeRF).")] = (
        Path(FRAMING_DATASETS[DEFAULT_FRAMING])
    ),
    cameras: Annotated[
        str | None, typer.Option(help="Training cameras, e.g. 1-18 or 1,4,8 (default: all "
                                      "training cameras).")
    ] = None,
    frame: Annotated[int, typer.Option(help="Frame index: the instant to reconstruct.")] = 0,
    seconds: Annotated[
        float, typer.Option(help="Training time budget (rendering and scoring not counted).")
    ] = 30.0,
    every: Annotated[
        float, typer.Option(help="Score the novel view every this many training seconds.")
    ] = 5.0,
    out: Annotated[
        Path | None, typer.Option(help="Write the final novel view here (PNG).")
    ] = None,
    device: Annotated[str, typer.Option(help="auto (CUDA when available), cpu or cuda.")] = (
        "auto"
    ),
    threads: Annotated[
        int | None, typer.Option(help="Torch CPU threads (default: torch's).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the initialisation and ray sampling.")] = 0,
) -> None:
    """Train a backend on one instant and score the held-out novel view as it goes."""

    from aoi3d.field import FieldTrainer, TrainView, field_config
    from aoi3d.lpips import load_lpips_fn
    from aoi3d.quality import psnr, ssim

    torch_device = _checked(backend, seconds, every, threads, device)
    try:
        ds = open_dataset(dataset)
    except (FileNotFoundError, ValueError, ImportError) as exc:
        fail(exc)
    try:
        ids = parse_cameras(cameras, ds) if cameras is not None else list(ds.train_ids)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--cameras") from exc
    if not 0 <= frame < ds.n_frames:
        raise typer.BadParameter(f"must be in 0..{ds.n_frames - 1}, got {frame}",
                                 param_hint="--frame")

    lpips_fn = load_lpips_fn()
    views = [TrainView(ds.cameras[c], ds.frame(c, frame)) for c in ids]
    camera = ds.cameras[ds.heldout_id]
    truth = ds.frame(ds.heldout_id, frame)
    cfg = field_config(backend) if threads is None else field_config(backend, num_threads=threads)
    from aoi3d.field.process import configure_process

    configure_process(cfg.num_threads, malloc=cfg.tune_malloc)
    trainer = FieldTrainer(cfg, ds.aabb, device=torch_device, seed=seed)
    trainer.set_views(views)
    console.print(f"[bold]{backend}[/] on {trainer.device}: {len(ids)} cameras {ids} at frame "
                  f"{frame}, novel view = camera {ds.heldout_id}, {ds.width}×{ds.height}, "
                  f"{seconds:g} s of training")

    image, train_s, lpips_note = _train_scoring(trainer, camera, truth, lpips_fn, seconds,
                                                every)
    rays_per_s = trainer.steps * cfg.batch_rays / train_s
    lp, _ = _lpips(image, truth, lpips_fn)
    console.print(f"[bold]novel view after {train_s:.1f} s[/] ({trainer.steps} steps, "
                  f"{rays_per_s:,.0f} rays/s): PSNR {psnr(image, truth):.2f} dB, SSIM "
                  f"{ssim(image, truth):.4f}, LPIPS {'—' if lp is None else f'{lp:.4f}'}")
    if lpips_note:
        console.print(f"LPIPS unavailable: {lpips_note}")
    if out is not None:
        from PIL import Image

        out.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(to_uint8(image), "RGB").save(out)
        console.print(f"novel view written to {out}")
