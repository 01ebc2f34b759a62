"""What the command groups share: option types and the one mechanism for a group's shared
options (:func:`with_shared_options`), ``KEY=VALUE`` overrides, an episode config from a base
and the options (:func:`episode_config`, with the device rule of :mod:`aoi3d.device`), the
console (:func:`make_console`: no emoji codes in user text), the number formatter of tables
(:func:`fmt`), the progress bar's columns, the experiments' dataset, the short label of a
policy in tables and figures, and the one-line error exit.

Light on purpose: every ``aoi3d`` command (``--help`` included) imports this module, so it
imports neither torch nor the experiment engine (those load inside the commands).
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import json
import math
import numbers
import signal
import sys
import threading
from collections.abc import Callable, Collection, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import typer

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import ProgressColumn

    from aoi3d.experiment import EpisodeConfig
    from aoi3d.scene import SceneDataset

__all__ = [
    "LpipsOpt",
    "ProcessesOpt",
    "ThreadsOpt",
    "episode_config",
    "fail",
    "fmt",
    "make_console",
    "open_experiment_dataset",
    "parse_sets",
    "progress_columns",
    "short_label",
    "stop_on_signal",
    "with_shared_options",
]

ProcessesOpt = Annotated[int | None, typer.Option(
    "--processes", "-j", "--workers",
    min=1, help="Local processes that run the episodes (default: all local cores). --workers "
                "is its old name, kept for one release: the pipeline's reconstruction workers "
                "are aoi3d up --workers.")]
ThreadsOpt = Annotated[int, typer.Option(min=1, help="Torch threads per episode process.")]
LpipsOpt = Annotated[bool, typer.Option(help="Score LPIPS too (when its weights are cached).")]


@contextlib.contextmanager
def stop_on_signal() -> Iterator[threading.Event]:
    """An event that Ctrl-C or SIGTERM sets while the block runs (a long-running command's way
    to stop cleanly); the previous handlers come back after it."""
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


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


def with_shared_options(options: Callable[..., None], bundle: Callable[..., Any], *,
                        omit: Collection[str] = ()
                        ) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """Make a command from ``body(shared, <its own options>)``: the command's options are the
    body's own followed by the parameters of ``options`` (a signature only; less ``omit``),
    and the body receives those as one ``bundle(**values)`` (``omitted`` ones are not passed).
    Register the result with ``app.command()``. The one way a command group shares options."""
    shared = [p for p in inspect.signature(options, eval_str=True).parameters.values()
              if p.name not in omit]
    names = [p.name for p in shared]

    def decorate(body: Callable[..., None]) -> Callable[..., None]:
        own = list(inspect.signature(body, eval_str=True).parameters.values())[1:]

        @functools.wraps(body)
        def command(**kwargs: Any) -> None:
            body(bundle(**{name: kwargs.pop(name) for name in names}), **kwargs)

        params = own + shared
        command.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
        command.__annotations__ = {p.name: p.annotation for p in params}
        return command

    return decorate


def episode_config(base: EpisodeConfig, changes: dict[str, Any], sets: Sequence[str] | None,
                   *, check_device: bool = True) -> EpisodeConfig:
    """``base`` with ``changes`` (the options given) and then the ``--set KEY=VALUE`` items
    applied; a bad value, an unknown backend or field key, or (``check_device``) a device
    this machine does not have (:func:`aoi3d.device.resolve_device`) is a
    ``typer.BadParameter``."""
    from aoi3d.device import resolve_device
    from aoi3d.experiment import EpisodeConfig
    from aoi3d.field import field_config

    try:
        cfg = EpisodeConfig.from_dict({**base.to_dict(), **changes, **parse_sets(sets)})
        field_config(cfg.backend, **cfg.field)  # unknown backend or field key: fail now
    except (TypeError, ValueError) as err:
        raise typer.BadParameter(str(err)) from None
    if check_device:
        try:
            resolve_device(cfg.device)
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="'--device'") from None
    return cfg


def make_console(*, stderr: bool = False, width: int | None = None) -> Console:
    """A console for a command's output: tables unwrapped in logs (160 columns when stdout
    is not a terminal, unless ``width``), and no emoji codes — policy specs and paths are
    printed as they are (Rich would turn ``mat:100:`` into ``mat💯``)."""
    from rich.console import Console

    if width is None and not sys.stdout.isatty():
        width = 160
    return Console(stderr=stderr, width=width, emoji=False)


def fmt(mean: float | None, half: float | None = None, digits: int = 2) -> str:
    """``mean ± half`` with ``digits`` decimals, ``mean`` alone without a finite ``half``, a
    whole number (a count) as it is, and ``—`` for a missing or non-finite value: the cells of
    every table."""
    if isinstance(mean, numbers.Integral) and not isinstance(mean, bool):
        return str(mean)
    if mean is None or not math.isfinite(mean):
        return "—"
    text = f"{mean:.{digits}f}"
    if half is not None and math.isfinite(half):
        text += f" ± {half:.{digits}f}"
    return text


def fail(message: object, code: int = 1) -> NoReturn:
    """Print ``error: <message>`` as one line on stderr (never wrapped) and exit ``code``."""
    typer.echo(f"error: {' '.join(str(message).split())}", err=True)
    raise typer.Exit(code)


def fail_lines(message: object, code: int = 1) -> NoReturn:
    """Print ``error: <line>`` for each line of ``message`` (a rig file's bad fields, one a
    line) on stderr and exit ``code``."""
    for line in str(message).splitlines() or [""]:
        typer.echo(f"error: {' '.join(line.split())}", err=True)
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
    from aoi3d.experiment.sweep import default_processes
    from aoi3d.scene import ensure_dataset, open_dataset
    from aoi3d.scene.framings import FRAMING_DATASETS, FRAMING_SCENES

    own = path.absolute() == Path(FRAMING_DATASETS["rotor"]).absolute()
    if path.exists() and not own:
        return open_dataset(path, verify=True)
    with console.status(f"scene dataset {path} (generated if missing or stale) …"):
        return ensure_dataset(path, FRAMING_SCENES["rotor"], processes=default_processes())


def short_label(spec: str) -> str:
    """A policy's name for a table or figure (:func:`aoi3d.policy.short_label`: its kind's
    short form, e.g. ``ppo:<folder>/<file>`` instead of the checkpoint's whole path)."""
    from aoi3d.policy import short_label as short

    return short(spec)


def control_headers() -> dict[str, str]:
    """``Authorization: Bearer …`` when a control token is configured for this shell's
    pipeline (``AOI3D_CONTROL_TOKEN_FILE`` or ``AOI3D_CONTROL_TOKEN``, as the services read
    it), else nothing: the CLI's REST calls then pass the services' guard."""
    import os

    path = os.environ.get("AOI3D_CONTROL_TOKEN_FILE")
    token = Path(path).read_text().strip() if path else os.environ.get("AOI3D_CONTROL_TOKEN")
    return {"Authorization": f"Bearer {token}"} if token else {}
