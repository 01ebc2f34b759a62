"""What the command groups share: option types, ``KEY=VALUE`` overrides, the progress bar's
columns, the experiments' dataset, the short label of a policy in tables and figures, and the
one-line error exit.

Light on purpose: every ``aoi3d`` command (``--help`` included) imports this module, so it
imports neither torch nor the experiment engine (those load inside the commands).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import typer

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import ProgressColumn

    from aoi3d.scene import SceneDataset

__all__ = [
    "LpipsOpt",
    "ThreadsOpt",
    "WorkersOpt",
    "fail",
    "open_experiment_dataset",
    "parse_sets",
    "progress_columns",
    "short_label",
]

WorkersOpt = Annotated[int | None, typer.Option(
    min=1, help="Worker processes (default: all local cores).")]
ThreadsOpt = Annotated[int, typer.Option(min=1, help="Torch threads per worker process.")]
LpipsOpt = Annotated[bool, typer.Option(help="Score LPIPS too (when its weights are cached).")]


def parse_sets(sets: Sequence[str] | None, option: str = "--set") -> dict[str, Any]:
    """``KEY=VALUE`` items as a dict, VALUE parsed as JSON where it parses (else the text)."""
    out: dict[str, Any] = {}
    for item in sets or ():
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise typer.BadParameter(f"expected KEY=VALUE, got {item!r}",
                                     param_hint=f"'{option}'")
        try:
            value: Any = json.loads(text)
        except json.JSONDecodeError:
            value = text
        out[key.strip()] = value
    return out


def fail(message: object, code: int = 1) -> NoReturn:
    """Print ``error: <message>`` as one line on stderr (never wrapped) and exit ``code``."""
    typer.echo(f"error: {' '.join(str(message).split())}", err=True)
    raise typer.Exit(code)


def progress_columns() -> tuple[ProgressColumn, ...]:
    """A sweep's progress bar: spinner, label, bar, done/total, elapsed, ETA."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        SpinnerColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return (SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
            MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("ETA"),
            TimeRemainingColumn())


def open_experiment_dataset(path: Path, console: Console) -> SceneDataset:
    """The experiments' own dataset folder is (re)generated when missing, damaged or of another
    scene config; any other folder is read as it is, every frame file checked (a bad one:
    :class:`~aoi3d.scene.DatasetError`), and generated with the experiments' scene only if it
    does not exist."""
    from aoi3d.experiment.sweep import default_workers
    from aoi3d.scene import ensure_dataset, open_dataset
    from aoi3d.scene.framings import FRAMING_DATASETS, FRAMING_SCENES

    own = path.absolute() == Path(FRAMING_DATASETS["rotor"]).absolute()
    if path.exists() and not own:
        return open_dataset(path, verify=True)
    with console.status(f"scene dataset {path} (generated if missing or stale) …"):
        return ensure_dataset(path, FRAMING_SCENES["rotor"], workers=default_workers())


def short_label(spec: str) -> str:
    """A policy's name for a table or figure: ``ppo:<folder>/<file>``, not the whole path."""
    if not spec.startswith("ppo:"):
        return spec
    path = Path(spec[len("ppo:"):])
    return f"ppo:{path.parent.name}/{path.name}" if path.parent.name else spec


def control_headers() -> dict[str, str]:
    """``Authorization: Bearer …`` when a control token is configured for this shell's
    pipeline (``AOI3D_CONTROL_TOKEN_FILE`` or ``AOI3D_CONTROL_TOKEN``, as the services read
    it), else nothing: the CLI's REST calls then pass the services' guard."""
    import os

    path = os.environ.get("AOI3D_CONTROL_TOKEN_FILE")
    token = Path(path).read_text().strip() if path else os.environ.get("AOI3D_CONTROL_TOKEN")
    return {"Authorization": f"Bearer {token}"} if token else {}
