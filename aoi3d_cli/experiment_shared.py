"""What every ``aoi3d experiment`` command shares: the options each takes after its own
(:func:`experiment_command`, :class:`Shared`), the run they set up
(:meth:`Shared.setup` → :class:`aoi3d.experiment.report.ExperimentRun`), and the sweeps and
oracle searches run with a progress bar (:func:`run`, :func:`run_oracle`).

The experiment engine (torch) is imported inside the functions that run it, so that
``aoi3d --help`` and the other commands start without it (tests/unit/cli/test_cli_startup.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from aoi3d.scene.framings import FRAMING_DATASETS
from aoi3d_cli.common import (
    LpipsOpt,
    ProcessesOpt,
    ThreadsOpt,
    episode_config,
    make_console,
    open_experiment_dataset,
    progress_columns,
    with_shared_options,
)

if TYPE_CHECKING:
    from aoi3d.experiment import Job, SweepOutcome
    from aoi3d.experiment.oracle import OracleSpec
    from aoi3d.experiment.report import ExperimentRun
    from aoi3d.experiment.sweep import OracleOutcome

console = make_console()

DatasetOpt = Annotated[Path | None, typer.Option(
    help="Scene dataset (any layout `aoi3d scene` reads); the experiments' scene (the rotor "
         "close-up at 6 rpm) is generated there if the folder does not exist. Default: "
         f"{FRAMING_DATASETS['rotor']}.")]
OutOpt = Annotated[Path | None, typer.Option(
    help="Output folder (CSV, JSON, PNG). Default: runs/experiments/<command>-<preset>.")]
CacheOpt = Annotated[Path, typer.Option(
    help="Episode cache shared by all commands (delete it to recompute everything).")]
SeedsOpt = Annotated[int | None, typer.Option(
    min=1, help="Independent simulations per point (default: the preset's).")]
SeedOffsetOpt = Annotated[int, typer.Option(
    min=0, help="First seed: the simulations use seeds OFFSET … OFFSET+S−1 (the same for "
                "every point, so differences are paired). Seeds 0–20 and 1000–1015 were used "
                "while developing; pick another block to check a result on unseen seeds.")]
StepsOpt = Annotated[int | None, typer.Option(
    min=1, help="Training steps per decision (default: the preset's).")]
CarryOpt = Annotated[str | None, typer.Option(
    help="Model between decisions: fresh (per-time: a new model per scored decision), "
         "warm (one model, rendered as it is) or fork (the live workers': a copy of the warm "
         "model trains --set render_steps=K steps on the scored decision's frames).")]
BackendOpt = Annotated[str | None, typer.Option(
    "--backend", "--field",
    help="Radiance-field backend (BACKENDS; `aoi3d field backends` lists them): grid, ngp, "
         "tensorf, nerf, nerfacto, or flow — the time-aware grid, whose render at the display "
         "time is taken at that time. --field is the same option.")]
RayOpt = Annotated[str | None, typer.Option(
    help="Run the episodes on Ray: an address (auto, ray://host:10001) or 'local'. Needs "
         "pip install '.[cluster]'.")]
SetOpt = Annotated[list[str] | None, typer.Option(
    "--set", help="Override any episode config field, KEY=VALUE (VALUE as JSON where it "
                  "parses), e.g. --set warmup_ms=600 --set field='{\"batch_rays\": 512}'.")]
DeviceOpt = Annotated[str | None, typer.Option(
    help="Torch device of the radiance field: cpu or cuda (default: the preset's, cpu).")]


def _shared_options(
    dataset: DatasetOpt = None,
    out: OutOpt = None,
    cache: CacheOpt = Path("runs/experiments/cache"),
    seeds: SeedsOpt = None,
    seed_offset: SeedOffsetOpt = 0,
    steps_per_epoch: StepsOpt = None,
    carry: CarryOpt = None,
    backend: BackendOpt = None,
    processes: ProcessesOpt = None,
    threads: ThreadsOpt = 1,
    ray_address: RayOpt = None,
    lpips: LpipsOpt = True,
    device: DeviceOpt = None,
    set_: SetOpt = None,
) -> None:
    """The options every experiment command takes after its own (a signature only: see
    :func:`experiment_command`)."""


def experiment_command(*, seeds: bool = True) -> Callable[[Callable[..., None]],
                                                          Callable[..., None]]:
    """An experiment command from ``body(shared: Shared, <its own options>)``
    (:func:`aoi3d_cli.common.with_shared_options`; without ``--seeds`` when ``seeds`` is
    False)."""
    return with_shared_options(_shared_options, Shared, omit=() if seeds else ("seeds",))


@dataclass(frozen=True)
class Shared:
    """The values of :func:`_shared_options` for one invocation."""

    dataset: Path | None
    out: Path | None
    cache: Path
    steps_per_epoch: int | None
    carry: str | None
    backend: str | None
    processes: int | None
    threads: int
    ray_address: str | None
    lpips: bool
    device: str | None
    set_: list[str] | None
    seed_offset: int = 0
    seeds: int | None = None

    def setup(self, command: str, preset: str, *, seeds: int | None = None) -> ExperimentRun:
        """Validate the options, open (or generate) the dataset and make the output folder;
        ``seeds``: the command's own seed count when it has no ``--seeds`` (default: the
        ``--seeds`` given, else the preset's)."""
        from aoi3d.experiment import ResultCache, default_processes, get_preset
        from aoi3d.experiment.report import ExperimentRun

        try:
            chosen = get_preset(preset)
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="'--preset'") from None
        changes: dict[str, Any] = {"lpips": self.lpips}
        for key, value in (("steps_per_epoch", self.steps_per_epoch), ("carry", self.carry),
                           ("backend", self.backend), ("device", self.device)):
            if value is not None:
                changes[key] = value
        if self.dataset is not None:
            changes["dataset"] = str(self.dataset)
        # the device is checked here unless a Ray cluster runs the episodes
        cfg = episode_config(chosen.episode, changes, self.set_,
                             check_device=self.ray_address is None)
        ds = open_experiment_dataset(Path(cfg.dataset), console)
        folder = (self.out if self.out is not None
                  else Path("runs/experiments") / f"{command}-{chosen.name}")
        folder.mkdir(parents=True, exist_ok=True)
        count = seeds if seeds is not None else self.seeds
        return ExperimentRun(
            command=command, preset=chosen, cfg=cfg, dataset=ds, out=folder,
            cache=ResultCache(self.cache), seeds=count if count is not None else chosen.seeds,
            processes=self.processes if self.processes is not None else default_processes(),
            threads=self.threads, ray_address=self.ray_address, started=time.time(),
            seed_offset=self.seed_offset,
        )


def run(setup: ExperimentRun, jobs: list[Job], label: str) -> SweepOutcome:
    """Run ``jobs`` (cached) with a progress bar; Ctrl-C keeps the finished episodes."""
    from rich.progress import Progress

    from aoi3d.experiment import run_jobs

    where = (f"Ray ({setup.ray_address})" if setup.ray_address
             else f"{min(setup.processes, len(jobs))} process(es) × {setup.threads} thread(s)")
    console.print(f"[bold]{label}[/]: {len(jobs)} episodes on {where}; cache {setup.cache.root}")
    try:
        with Progress(*progress_columns(), console=console, transient=False) as bar:
            task = bar.add_task(label, total=None)

            def report(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            outcome = run_jobs(setup.cfg, jobs, cache=setup.cache, processes=setup.processes,
                               threads_per_process=setup.threads,
                               ray_address=setup.ray_address, progress=report,
                               dataset=setup.dataset)
    except KeyboardInterrupt:
        console.print(f"[yellow]interrupted[/]: finished episodes are kept in "
                      f"{setup.cache.root}; run the same command again to resume")
        raise typer.Exit(130) from None
    console.print(f"{outcome.computed} episode(s) computed, {outcome.cached} from the cache, "
                  f"{outcome.wall_s:.1f} s")
    return outcome


def run_oracle(setup: ExperimentRun, oracle: OracleSpec, delay: str) -> OracleOutcome:
    """The oracle bound's search on the setup's seeds, with a progress bar per round."""
    from rich.progress import Progress

    from aoi3d.experiment import run_oracle as search

    where = (f"Ray ({setup.ray_address})" if setup.ray_address
             else f"{setup.processes} process(es) × {setup.threads} thread(s)")
    console.print(f"[bold]{oracle.spec}[/] (a bound, searched with the truth): "
                  f"{setup.seeds} seed(s) on {where}; cache {setup.cache.root}")
    try:
        with Progress(*progress_columns(), console=console, transient=False) as bar:
            task = bar.add_task(oracle.spec, total=None)

            def round_(text: str) -> None:
                bar.update(task, description=text, completed=0, total=None)

            def report(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            outcome = search(setup.cfg.with_(delay=delay), oracle, setup.seed_list,
                             cache=setup.cache, processes=setup.processes,
                             threads_per_process=setup.threads,
                             ray_address=setup.ray_address, progress=report,
                             on_round=round_, dataset=setup.dataset)
    except KeyboardInterrupt:
        console.print(f"[yellow]interrupted[/]: the candidates evaluated are kept in "
                      f"{setup.cache.root}; run the same command again to resume")
        raise typer.Exit(130) from None
    console.print(f"{oracle.spec}: {outcome.reconstructions} reconstruction(s) "
                  f"({outcome.computed} computed, {outcome.cached} from the cache), "
                  f"{outcome.wall_s:.1f} s")
    return outcome
