"""``aoi3d experiment …``: the paper's tradeoff figures, each with one command.

Every command runs a sweep of episodes (:mod:`aoi3d.experiment`) on all local cores (or a
Ray cluster with ``--ray-address``), caches each episode under ``--cache`` (an interrupted
sweep resumes; a re-run computes only what is missing; commands share episodes), and writes
CSV, JSON (with the full config, the code version and the machine) and PNG figures to
``--out``.

The experiment engine (torch), the figures (matplotlib) and the channel (scipy) are imported
inside the commands, so that ``aoi3d --help`` and the other commands start without them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer
from rich.table import Table

from aoi3d.numbers import format_number
from aoi3d.scene.framings import FRAMING_DATASETS
from aoi3d_cli.common import (
    LpipsOpt,
    ThreadsOpt,
    WorkersOpt,
    episode_config,
    fmt,
    make_console,
    open_experiment_dataset,
    progress_columns,
    short_label,
    with_shared_options,
)

if TYPE_CHECKING:
    from aoi3d.experiment import (
        EpisodeConfig,
        EpisodeResult,
        Job,
        Preset,
        ResultCache,
        SweepOutcome,
    )
    from aoi3d.experiment.optimum import Optimum
    from aoi3d.scene import SceneDataset

PRESET_NAMES = ("quick", "paper")
"""The names of :data:`aoi3d.experiment.PRESETS`, for ``--help`` without importing the engine
(a test keeps them equal)."""

app = typer.Typer(no_args_is_help=True, add_completion=False)
console = make_console()


@app.callback()
def experiment() -> None:
    """Sweeps and figures of the timeliness–fidelity tradeoff on a virtual clock."""


# --- options shared by every command ---------------------------------------------------------
PresetOpt = Annotated[str, typer.Option(
    help=f"Budget preset: {', '.join(PRESET_NAMES)} (quick: ≤ 10 min on 2 cores; paper: Γ every "
         "10 ms, 40 simulations per point).")]
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
         "warm (one model, rendered as it is) or fork (the live trainer's: a copy of the warm "
         "model trains --set render_steps=K steps on the scored decision's frames).")]
BackendOpt = Annotated[str | None, typer.Option(help="Radiance-field backend (BACKENDS).")]
RayOpt = Annotated[str | None, typer.Option(
    help="Run the episodes on Ray: an address (auto, ray://host:10001) or 'local'. Needs "
         "pip install '.[cluster]'.")]
SetOpt = Annotated[list[str] | None, typer.Option(
    "--set", help="Override any episode config field, KEY=VALUE (VALUE as JSON where it "
                  "parses), e.g. --set warmup_ms=600 --set field='{\"batch_rays\": 512}'.")]
DelayOpt = Annotated[str, typer.Option(help="Delay spec of the links, e.g. exp:60 (ms).")]
DeviceOpt = Annotated[str | None, typer.Option(
    help="Torch device of the radiance field: cpu or cuda (default: the preset's, cpu).")]


@dataclass
class _Setup:
    command: str
    preset: Preset
    cfg: EpisodeConfig
    dataset: SceneDataset
    out: Path
    cache: ResultCache
    seeds: int
    workers: int
    threads: int
    ray_address: str | None
    started: float
    seed_offset: int = 0

    @property
    def seed_list(self) -> list[int]:
        """The seeds of every point: ``seed_offset … seed_offset + seeds − 1``."""
        return list(range(self.seed_offset, self.seed_offset + self.seeds))


def _int_list(text: str | None, name: str) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        values = tuple(int(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated whole ms, got {text!r}",
                                 param_hint=name) from None
    if not values or min(values) < 0:
        raise typer.BadParameter(f"expected values >= 0, got {text!r}", param_hint=name)
    return values


def _delay(spec: str, name: str = "'--delay'") -> str:
    from aoi3d.channel import DelaySpecError, parse_channel

    try:
        return parse_channel(spec).spec
    except DelaySpecError as err:
        raise typer.BadParameter(str(err), param_hint=name) from None


def _spec_list(text: str) -> list[str]:
    """Specs separated by ``;`` when the text holds one (a regimes schedule or a trace's
    options hold commas), else by commas."""
    sep = ";" if ";" in text else ","
    return [d.strip() for d in text.split(sep) if d.strip()]


def _shared_options(
    dataset: DatasetOpt = None,
    out: OutOpt = None,
    cache: CacheOpt = Path("runs/experiments/cache"),
    seeds: SeedsOpt = None,
    seed_offset: SeedOffsetOpt = 0,
    steps_per_epoch: StepsOpt = None,
    carry: CarryOpt = None,
    backend: BackendOpt = None,
    workers: WorkersOpt = None,
    threads: ThreadsOpt = 1,
    ray_address: RayOpt = None,
    lpips: LpipsOpt = True,
    device: DeviceOpt = None,
    set_: SetOpt = None,
) -> None:
    """The options every experiment command takes after its own (a signature only: see
    :func:`_experiment_command`)."""


def _experiment_command(*, seeds: bool = True) -> Callable[[Callable[..., None]],
                                                           Callable[..., None]]:
    """An experiment command from ``body(shared: _Shared, <its own options>)``
    (:func:`aoi3d_cli.common.with_shared_options`; without ``--seeds`` when ``seeds`` is
    False)."""
    return with_shared_options(_shared_options, _Shared, omit=() if seeds else ("seeds",))


@dataclass(frozen=True)
class _Shared:
    """The values of :func:`_shared_options` for one invocation."""

    dataset: Path | None
    out: Path | None
    cache: Path
    steps_per_epoch: int | None
    carry: str | None
    backend: str | None
    workers: int | None
    threads: int
    ray_address: str | None
    lpips: bool
    device: str | None
    set_: list[str] | None
    seed_offset: int = 0
    seeds: int | None = None

    def setup(self, command: str, preset: str, *, seeds: int | None = None) -> _Setup:
        """Validate the options, open (or generate) the dataset and make the output folder;
        ``seeds``: the command's own seed count when it has no ``--seeds`` (default: the
        ``--seeds`` given, else the preset's)."""
        from aoi3d.experiment import ResultCache, default_workers, get_preset

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
        return _Setup(
            command=command, preset=chosen, cfg=cfg, dataset=ds, out=folder,
            cache=ResultCache(self.cache), seeds=count if count is not None else chosen.seeds,
            workers=self.workers if self.workers is not None else default_workers(),
            threads=self.threads, ray_address=self.ray_address, started=time.time(),
            seed_offset=self.seed_offset,
        )


def _run(setup: _Setup, jobs: list[Job], label: str) -> SweepOutcome:
    from rich.progress import Progress

    from aoi3d.experiment import run_jobs

    where = (f"Ray ({setup.ray_address})" if setup.ray_address
             else f"{min(setup.workers, len(jobs))} process(es) × {setup.threads} thread(s)")
    console.print(f"[bold]{label}[/]: {len(jobs)} episodes on {where}; cache {setup.cache.root}")
    try:
        with Progress(*progress_columns(), console=console, transient=False) as bar:
            task = bar.add_task(label, total=None)

            def report(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            outcome = run_jobs(setup.cfg, jobs, cache=setup.cache, workers=setup.workers,
                               threads_per_worker=setup.threads,
                               ray_address=setup.ray_address, progress=report,
                               dataset=setup.dataset)
    except KeyboardInterrupt:
        console.print(f"[yellow]interrupted[/]: finished episodes are kept in "
                      f"{setup.cache.root}; run the same command again to resume")
        raise typer.Exit(130) from None
    console.print(f"{outcome.computed} episode(s) computed, {outcome.cached} from the cache, "
                  f"{outcome.wall_s:.1f} s")
    return outcome


def _episode_rows(results: Sequence[EpisodeResult]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.to_dict().items() if k != "epochs"} for r in results]


def _write(setup: _Setup, outcomes: Sequence[SweepOutcome], args: dict[str, Any],
           episodes: Sequence[EpisodeResult], csvs: dict[str, Sequence[dict[str, Any]]],
           **doc: Any) -> None:
    """What every command writes to ``setup.out``: the CSVs in ``csvs`` (file name → rows),
    ``episodes.csv`` (one row per episode) and ``results.json`` (``meta`` — the command, its
    arguments, the config, the code version and the machine —, then ``doc``, then the
    episodes with their per-decision scores)."""
    from aoi3d.experiment.report import write_csv, write_json

    meta = _meta(setup, outcomes, args)
    for name, rows in csvs.items():
        write_csv(setup.out / name, rows)
    write_csv(setup.out / "episodes.csv", _episode_rows(episodes))
    write_json(setup.out / "results.json", {"meta": meta, **doc,
                                            "episodes": [r.to_dict() for r in episodes]})


def _check_metric(metric: str, hint: str) -> None:
    if metric not in OPTIMUM_METRICS:
        raise typer.BadParameter(f"unknown metric {metric!r}; accepted: "
                                 f"{', '.join(OPTIMUM_METRICS)}",
                                 param_hint=hint)


def _meta(setup: _Setup, outcomes: Sequence[SweepOutcome], args: dict[str, Any]
          ) -> dict[str, Any]:
    from aoi3d.experiment.report import code_version, machine
    from aoi3d.experiment.sweep import lpips_available

    episode_s = [r.wall_s for o in outcomes for r in o.results]
    return {
        "command": f"aoi3d experiment {setup.command}",
        "args": args,
        "preset": setup.preset.to_dict(),
        "episode_config": setup.cfg.to_dict(),
        "lpips": lpips_available(setup.cfg),
        "seeds": setup.seeds,
        "seed_offset": setup.seed_offset,
        "seed_list": setup.seed_list,
        "workers": setup.workers if setup.ray_address is None else None,
        "threads_per_worker": setup.threads,
        "ray_address": setup.ray_address,
        "code_version": code_version(),
        "machine": machine(),
        "wall_s": time.time() - setup.started,
        "episodes_computed": sum(o.computed for o in outcomes),
        "episodes_cached": sum(o.cached for o in outcomes),
        "episode_wall_s_mean": float(np.mean(episode_s)) if episode_s else None,
    }


def _seed_span(setup: _Setup) -> str:
    first, last = setup.seed_list[0], setup.seed_list[-1]
    return f"{first}" if first == last else f"{first}–{last}"


def _table(rows: Sequence[dict[str, Any]], first: str, title: str) -> None:
    table = Table(title=title)
    for name in (first, "n", "PSNR (dB)", "dynamic PSNR (dB)", "SSIM", "LPIPS", "reward",
                 "cameras", "AoI used (ms)"):
        table.add_column(name, justify="right")
    for r in rows:
        table.add_row(str(r[first]), str(r["n"]), fmt(r["psnr_db"], r["psnr_db_ci95"]),
                      fmt(r["psnr_dynamic_db"], r["psnr_dynamic_db_ci95"]),
                      fmt(r["ssim"], r["ssim_ci95"], 3), fmt(r["lpips"], r["lpips_ci95"], 3),
                      fmt(r["reward"], r["reward_ci95"], 3),
                      fmt(r["n_selected"], None, 1), fmt(r["aoi_used_ms"], None, 0))
    console.print(table)


@dataclass(frozen=True)
class _MatSweep:
    """A MAT sweep's policies, by the label their results carry: ``MatPolicy(Γ)`` for each Γ,
    then ``AllPolicy`` (the reference, at Γ = ∞). Γ is read from the policy objects built
    here, never parsed back out of a label."""

    policies: dict[str, Any]

    @classmethod
    def of(cls, gammas: Sequence[float]) -> _MatSweep:
        from aoi3d.policy import AllPolicy, MatPolicy

        built = [MatPolicy(float(g)) for g in gammas] + [AllPolicy()]
        return cls({p.spec: p for p in built})

    def gamma(self, label: str) -> float | None:
        """Γ (ms) of the sweep's policy ``label``; None for the reference."""
        return self.policies[label].gamma_ms

    def candidate(self, label: str) -> Any:
        """A tradeoff candidate: Γ in ms for a MAT point, else the label (``all``)."""
        gamma = self.gamma(label)
        return label if gamma is None else gamma

    def position(self) -> dict[Any, float]:
        """Where each candidate lies along the sweep: Γ, and ∞ for the reference."""
        return {self.candidate(label): math.inf if p.gamma_ms is None else p.gamma_ms
                for label, p in self.policies.items()}

    def jobs(self, delays: Sequence[str], seeds: Sequence[int]) -> list[Job]:
        from aoi3d.experiment import Job

        return [Job(label, d, s) for s in seeds for d in delays for label in self.policies]


def _tradeoff_rows(results: Sequence[EpisodeResult], sweep: _MatSweep
                   ) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    from aoi3d.experiment import aggregate

    rows = aggregate(results)
    points = []
    reference = None
    for row in rows:
        gamma = sweep.gamma(row["policy"])
        if gamma is None:
            reference = row
        else:
            points.append({"gamma_ms": gamma, **row})
    points.sort(key=lambda r: r["gamma_ms"])
    return points, reference


def _best_gamma(points: Sequence[dict[str, Any]], metric: str = "psnr_db") -> float:
    """The swept Γ with the best mean ``metric`` (highest; lowest for a lower-is-better one,
    LPIPS)."""
    from aoi3d.experiment.optimum import sign_of

    sign = sign_of(metric)
    values = np.array([np.nan if p[metric] is None else sign * p[metric] for p in points],
                      float)
    if not np.isfinite(values).any():
        raise RuntimeError(f"no finite {metric} in the sweep")
    return float(points[int(np.nanargmax(values))]["gamma_ms"])


def _optima(results: Sequence[EpisodeResult], *, sweep: _MatSweep | None = None
            ) -> dict[str, Optimum]:
    """Per metric of :data:`OPTIMUM_METRICS`, :func:`aoi3d.experiment.optimum.optima` over the
    policies of ``results`` (one delay), paired by seed: the points of a MAT ``sweep`` (its
    candidates are Γ, ordered along it), or, without one, policies by their label
    (unordered)."""
    from aoi3d.experiment.optimum import optima

    label: Callable[[str], Any] = sweep.candidate if sweep is not None else str

    selects: dict[Any, list[float]] = {}
    for r in results:
        selects.setdefault(label(r.policy), []).append(float(r.n_selected))
    rows = [{"candidate": label(r.policy), "seed": r.seed,
             **{m: getattr(r, m) for m in OPTIMUM_METRICS}} for r in results]
    return optima(rows, OPTIMUM_METRICS, candidate=lambda row: row["candidate"],
                  selects={c: float(np.mean(v)) for c, v in selects.items()},
                  ordered=sweep is not None,
                  position=sweep.position() if sweep is not None else None)


def _fmt_candidates(members: Sequence[Any]) -> str:
    return ", ".join(f"{m:g}" if isinstance(m, float) else str(m) for m in members)


def _print_optima(optima: dict[str, Optimum], unit: str = "Γ") -> None:
    for metric, opt in optima.items():
        if opt.ends:
            inside = [e for e in opt.ends if e in opt.members]
            verdict = ("[green]interior[/]" if opt.interior else
                       f"[yellow]not interior[/] ({_fmt_candidates(inside)}, an end of the "
                       f"sweep, is not significantly worse)")
        else:
            verdict = ""
        console.print(f"{metric}: best {unit} = {_fmt_candidates([opt.best])}; optimum set "
                      f"(not significantly worse, paired over {len(opt.seeds)} seeds): "
                      f"{{{_fmt_candidates(opt.members)}}} {verdict}")


MAT_BEST = "mat:best"
"""The ``compare --policy`` value for MAT at the best Γ of the tradeoff sweep (or
``--mat-ms``): the command's placeholder, resolved to a ``MatPolicy`` with that Γ."""

OPTIMUM_METRICS = ("psnr_db", "ssim", "lpips", "reward", "psnr_dynamic_db", "ssim_dynamic")
"""Metrics an optimum can be taken over (their direction:
:data:`aoi3d.experiment.optimum.LOWER_IS_BETTER`); ``*_dynamic*``: over the dynamic region
(:mod:`aoi3d.quality`)."""


# --- commands --------------------------------------------------------------------------------
@app.command()
@_experiment_command()
def tradeoff(
    shared: _Shared,
    preset: PresetOpt = "quick",
    gammas: Annotated[str | None, typer.Option(
        help="MAT thresholds Γ in ms, comma-separated (default: the preset's).")] = None,
    delay: DelayOpt = "exp:60",
) -> None:
    """Fig. 4: PSNR, SSIM and LPIPS against the MAT Γ (mean of S simulations, 95% band),
    with the cameras used and the AoI of the used frames; `all` as the reference."""
    from aoi3d.channel import parse_channel
    from aoi3d.experiment.figures import plot_tradeoff

    setup = shared.setup("tradeoff", preset)
    gamma_list = _int_list(gammas, "'--gammas'") or setup.preset.gammas_ms
    delay = _delay(delay)
    sweep = _MatSweep.of(gamma_list)
    outcome = _run(setup, sweep.jobs([delay], setup.seed_list), "tradeoff")
    points, reference = _tradeoff_rows(outcome.results, sweep)
    best = _best_gamma(points)
    optima = _optima(outcome.results, sweep=sweep)
    _write(setup, [outcome], {"gammas_ms": list(gamma_list), "delay": delay}, outcome.results,
           {"points.csv": points + ([reference] if reference else [])},
           best_gamma_ms=best, optimum={m: o.to_dict() for m, o in optima.items()},
           points=points, reference=reference)
    mean_y = parse_channel(delay).mean_ms
    plot_tradeoff(points, setup.out / "tradeoff.png", reference=reference, title=(
        f"Quality of the novel view vs MAT Γ — E[Y] = {mean_y:g} ms, "
        f"C = {setup.cfg.period_ms} ms, N = {setup.cfg.n_cameras or len(setup.dataset.train_ids)}, "
        f"S = {setup.seeds} (seeds {_seed_span(setup)}), {setup.cfg.carry} model, "
        f"{setup.cfg.steps_per_epoch} steps/decision"))
    _table(points + ([{"gamma_ms": "all", **reference}] if reference else []), "gamma_ms",
           f"tradeoff at {delay} (mean ± 95% CI over seeds {_seed_span(setup)})")
    _print_optima(optima)
    console.print(f"results in {setup.out}")


@app.command()
@_experiment_command(seeds=False)
def views(
    shared: _Shared,
    preset: PresetOpt = "quick",
    gammas: Annotated[str | None, typer.Option(
        help="Γ values to show, comma-separated (default: the preset's).")] = None,
    rows: Annotated[int, typer.Option(min=1, help="Seeds shown, one row each.")] = 1,
    delay: DelayOpt = "exp:60",
) -> None:
    """Fig. 5: the novel view for several Γ (and `all`) next to the ground truth, at the last
    scored decision of an episode."""
    from PIL import Image

    from aoi3d.experiment.figures import plot_views

    setup = shared.setup("views", preset, seeds=rows)
    gamma_list = _int_list(gammas, "'--gammas'") or setup.preset.view_gammas_ms
    delay = _delay(delay)
    sweep = _MatSweep.of(gamma_list)
    outcome = _run(setup, sweep.jobs([delay], setup.seed_list), "views")
    ds = setup.dataset
    grid: list[list[tuple[str, np.ndarray]]] = []
    saved = []
    for old in setup.out.glob("view_seed*.png"):  # renders of an earlier run of this folder
        old.unlink()
    for seed in setup.seed_list:
        members = [(r, p, k) for r, p, k in zip(outcome.results, outcome.plans, outcome.keys,
                                                strict=True) if r.seed == seed]
        plan = members[0][1]
        last = [d for d in plan.decisions if d.scored][-1]
        truth_index = ds.frame_index(last.eval_ms + plan.scene_offset_ms)
        row = [(f"truth, t = {last.eval_ms} ms", ds.frame(ds.heldout_id, truth_index))]
        for result, _, key in members:
            png = setup.cache.render_png(key)
            if png is None:
                raise RuntimeError(f"render of {result.policy} missing from the cache ({key})")
            name = setup.out / f"view_seed{seed}_{result.policy.replace(':', '')}.png"
            name.write_bytes(png)
            saved.append(name.name)
            image = np.asarray(Image.open(name).convert("RGB"))
            score = result.epochs[-1]
            gamma = sweep.gamma(result.policy)
            label = "all" if gamma is None else f"Γ = {format_number(gamma)} ms"
            row.append((f"{label}\n{score.psnr_db:.1f} dB, {score.n_selected} cams", image))
        grid.append(row)
    _write(setup, [outcome], {"gammas_ms": list(gamma_list), "delay": delay, "rows": rows},
           outcome.results, {}, renders=saved)
    plot_views(grid, setup.out / "views.png", title=(
        f"Novel view (camera {ds.heldout_id}) vs MAT Γ at {delay}, {setup.cfg.carry} model"))
    console.print(f"views in {setup.out / 'views.png'}")


@app.command("delay")
@_experiment_command()
def delay_cmd(
    shared: _Shared,
    preset: PresetOpt = "quick",
    delays: Annotated[str | None, typer.Option(
        help="Delay specs, comma-separated, e.g. exp:20,exp:60 (default: the preset's); "
             "separated by ';' when a spec holds commas, e.g. "
             "'trace:T.up,offset=0;trace:T.up,offset=10000'.")] = None,
    gammas: Annotated[str | None, typer.Option(
        help="Γ values searched, comma-separated ms (default: the preset's).")] = None,
    metric: Annotated[str, typer.Option(
        help="What the optimal Γ optimises: psnr_db, ssim, reward, psnr_dynamic_db, "
             "ssim_dynamic (the dynamic region's; maximised) or lpips (minimised). The others' "
             "optima are written too.")] = "psnr_db",
) -> None:
    """Fig. 6: the optimal Γ (highest mean PSNR, or ``--metric``) against the mean delay."""
    from aoi3d.channel import parse_channel
    from aoi3d.experiment import Job
    from aoi3d.experiment.figures import plot_delay

    _check_metric(metric, "'--metric'")
    setup = shared.setup("delay", preset)
    if shared.seeds is None:
        setup.seeds = setup.preset.delay_seeds
    delay_list = ([_delay(d, "'--delays'") for d in _spec_list(delays)]
                  if delays else list(setup.preset.delays))
    gamma_list = _int_list(gammas, "'--gammas'") or setup.preset.delay_gammas_ms
    sweep = _MatSweep.of(gamma_list)
    jobs = [Job(label, d, s) for s in setup.seed_list for d in delay_list
            for label in sweep.policies if sweep.gamma(label) is not None]  # no reference
    outcome = _run(setup, jobs, "delay")
    curves = []
    optima = []
    for d in delay_list:
        points, _ = _tradeoff_rows([r for r in outcome.results if r.delay == d], sweep)
        curves.extend(points)
        row: dict[str, Any] = {"delay": d, "mean_delay_ms": parse_channel(d).mean_ms,
                               "metric": metric}
        for name, opt in _optima([r for r in outcome.results if r.delay == d],
                                 sweep=sweep).items():
            by_gamma = {p["gamma_ms"]: p for p in points}
            span = opt.range_of() or (math.nan, math.nan)
            suffix = "" if name == metric else f"_{name}"
            row.update({f"best_gamma_ms{suffix}": opt.best,
                        f"best{suffix or '_value'}": by_gamma[opt.best][name],
                        f"best_ci95{suffix}": by_gamma[opt.best][f"{name}_ci95"],
                        f"optimum_min_ms{suffix}": span[0],
                        f"optimum_max_ms{suffix}": span[1],
                        f"interior{suffix}": opt.interior})
            if name == metric:
                row["optimum"] = opt.to_dict()
        optima.append(row)
    _write(setup, [outcome], {"delays": delay_list, "gammas_ms": list(gamma_list)},
           outcome.results, {"optima.csv": [{k: v for k, v in o.items() if k != "optimum"}
                                             for o in optima], "curves.csv": curves},
           optima=optima, curves=curves)
    plot_delay(optima, curves, setup.out / "delay.png", metric=metric, title=(
        f"Optimal MAT Γ vs mean delay — C = {setup.cfg.period_ms} ms, S = {setup.seeds} "
        f"(seeds {_seed_span(setup)}), {setup.cfg.carry} model; bars: the optimum set"))
    table = Table(title=f"optimal Γ per delay (best mean {metric}; seeds {_seed_span(setup)})")
    for name in ("delay", "E[Y] (ms)", "best Γ (ms)", metric,
                 "optimum set: Γ not significantly worse (paired)", "interior"):
        table.add_column(name, justify="right")
    for o in optima:
        table.add_row(o["delay"], f"{o['mean_delay_ms']:g}", f"{o['best_gamma_ms']:g}",
                      fmt(o["best_value"], o["best_ci95"], 3),
                      f"{o['optimum_min_ms']:g}–{o['optimum_max_ms']:g}",
                      "yes" if o["interior"] else "no")
    console.print(table)
    console.print(f"results in {setup.out}")


@app.command()
@_experiment_command()
def compare(
    shared: _Shared,
    preset: PresetOpt = "quick",
    policy: Annotated[list[str] | None, typer.Option(
        "--policy", help="Policy spec (repeat): all, mat:<ms>, mat:best, freshest:<k>, "
                         "wait:<ms>, or any registered kind; a baseline of the follow-up "
                         "paper, tembed[:<features>[:<scale_ms>]] (timeliness embedding) or "
                         "wsum:<tau_ms> (weighted sum), each optionally @<policy> (default "
                         "@all); or the oracle bound, oracle[:rules|greedy[:<metric>]] "
                         "(searched with the truth: a bound, not a policy). Default: the "
                         "preset's.")] = None,
    mat_ms: Annotated[float | None, typer.Option(
        help="Γ for mat:best; default: the best Γ of the preset's tradeoff sweep (cached).")]
    = None,
    best_metric: Annotated[str, typer.Option(
        help="What mat:best's Γ is best at in the tradeoff sweep: psnr_db, ssim, reward, "
             "psnr_dynamic_db, ssim_dynamic (maximised) or lpips (minimised).")] = "psnr_db",
    delay: DelayOpt = "exp:60",
) -> None:
    """All policies side by side on the same seeds (same channel draws, same model seeds).

    ``ppo:<checkpoint>`` applies a trained agent's deterministic action at every decision.
    ``tembed`` and ``wsum:<τ>`` train the field on the policy's frames (``all`` by default)
    with the follow-up paper's timeliness embedding or age-weighted loss
    (:mod:`aoi3d.experiment.baselines`). ``oracle`` is the bound: at each scored decision, the
    best selection found by search with the true reward (:mod:`aoi3d.experiment.oracle`),
    reported beside the policies with every policy's paired distance to it, and left out of
    the policies' optimum set."""
    from aoi3d.experiment import Job, aggregate
    from aoi3d.experiment.baselines import (
        TrainerSpecError,
        baseline_label,
        is_trainer_spec,
        split_baseline,
    )
    from aoi3d.experiment.figures import plot_compare
    from aoi3d.experiment.oracle import OracleSpecError, is_oracle_spec, parse_oracle
    from aoi3d.field import field_config
    from aoi3d.policy import MatPolicy

    _check_metric(best_metric, "'--best-metric'")
    setup = shared.setup("compare", preset)
    delay = _delay(delay)
    specs = list(policy) if policy else list(setup.preset.compare)
    n_cameras = setup.cfg.n_cameras or len(setup.dataset.train_ids)
    oracles = []
    # (trainer option, policy) per spec; the policy None stands for mat:best, whose Γ (a
    # number) is known once the tradeoff sweep has run
    entries: list[tuple[Any, Any]] = []
    for spec in specs:  # validate every spec before any sweep runs
        if is_oracle_spec(spec):
            try:
                oracle = parse_oracle(spec)
            except OracleSpecError as err:
                raise typer.BadParameter(str(err), param_hint="'--policy'") from None
            if setup.cfg.carry != "fresh":
                raise typer.BadParameter(
                    f"{spec}: the oracle searches each scored decision on its own, which needs "
                    f"--carry fresh (a fresh model per scored decision), not "
                    f"{setup.cfg.carry!r}", param_hint="'--policy'")
            oracles.append(oracle)
            continue
        trainer = None
        policy_spec = spec
        if is_trainer_spec(spec):
            try:
                option, policy_spec = split_baseline(spec)
            except TrainerSpecError as err:
                raise typer.BadParameter(str(err), param_hint="'--policy'") from None
            try:
                field_config(setup.cfg.backend, **{**setup.cfg.field,
                                                   **option.field_overrides()})
            except (TypeError, ValueError) as err:
                raise typer.BadParameter(
                    f"{spec}: the {setup.cfg.backend!r} backend cannot take it ({err}); the "
                    "timeliness embedding (tembed) needs the grid backend",
                    param_hint="'--policy'") from None
            trainer = option
        entries.append((trainer, None if policy_spec == MAT_BEST
                        else _check_policy(policy_spec, n_cameras, spec)))
    outcomes = []
    if any(p is None for _, p in entries) and mat_ms is None:
        mat_sweep = _MatSweep.of(setup.preset.gammas_ms)
        sweep = _run(setup, mat_sweep.jobs([delay], setup.seed_list), "tradeoff (for mat:best)")
        outcomes.append(sweep)
        mat_ms = _best_gamma(_tradeoff_rows(sweep.results, mat_sweep)[0], best_metric)
    # each run's label and its own JSON: the policy's to_json(), inside its trainer option's
    # for a baseline (results carry it beside the label: kind, mat_ms … stay numbers)
    resolved: dict[tuple[str | None, str], None] = {}
    as_json: dict[str, dict[str, Any]] = {}
    for trainer, p in entries:
        pol = MatPolicy(mat_ms) if p is None else p
        resolved[None if trainer is None else trainer.spec, pol.spec] = None
        if trainer is None:
            as_json[pol.spec] = pol.to_json()
        else:
            as_json[baseline_label(trainer, pol.spec)] = {**trainer.to_json(),
                                                          "policy": pol.to_json()}
    as_json.update({o.spec: o.to_json() for o in oracles})
    results: list[EpisodeResult] = []
    if resolved:
        outcome = _run(setup, [Job(p, delay, s, trainer=t) for s in setup.seed_list
                               for t, p in resolved], "compare")
        outcomes.append(outcome)
        results = list(outcome.results)
    labels = list(dict.fromkeys(r.policy for r in results))
    bounds = []
    for oracle in dict.fromkeys(oracles):
        bounds.append(_run_oracle(setup, oracle, delay))
    rows = aggregate(results + [r for b in bounds for r in b.results])
    bound_labels = {b.spec for b in bounds}
    for row in rows:
        row["bound"] = row["policy"] in bound_labels
    optima = _optima(results) if results else {}
    bound_doc = {b.spec: _bound_doc(b, results) for b in bounds}
    _write(setup, outcomes, {"policies": labels, "oracles": [b.spec for b in bounds],
                             "delay": delay, "mat_best_ms": mat_ms,
                             "best_metric": best_metric},
           results + [r for b in bounds for r in b.results], {"compare.csv": rows},
           policies=[{**r, "policy_json": as_json.get(r["policy"])} for r in rows],
           optimum={m: o.to_dict() for m, o in optima.items()}, bound=bound_doc)
    plot_compare([{**r, "policy": short_label(r["policy"])} for r in rows],
                 setup.out / "compare.png", title=(
        f"Policies at {delay}, S = {setup.seeds} (the same seeds, {_seed_span(setup)}), "
        f"{setup.cfg.carry} model"))
    _table(rows, "policy", f"policies at {delay} (mean ± 95% CI over seeds {_seed_span(setup)})")
    _print_optima(optima, unit="policy")
    for b in bounds:
        _print_bound(b, bound_doc[b.spec])
    console.print(f"results in {setup.out}")


def _check_policy(spec: str, n_cameras: int, given: str) -> Any:
    """The policy of ``spec``; ``typer.BadParameter`` unless it is one that fits
    ``n_cameras``."""
    from aoi3d.policy import PolicySpecError, parse_policy

    try:
        policy = parse_policy(spec)
        policy.check_fits(n_cameras)  # e.g. a ppo checkpoint for another N
        return policy
    except PolicySpecError as err:
        where = "" if spec == given else f"in {given!r}: "
        raise typer.BadParameter(f"{where}{err}", param_hint="'--policy'") from None


def _run_oracle(setup: _Setup, oracle: Any, delay: str) -> Any:
    """The oracle bound's search on the setup's seeds, with a progress bar per round."""
    from rich.progress import Progress

    from aoi3d.experiment import run_oracle

    where = (f"Ray ({setup.ray_address})" if setup.ray_address
             else f"{setup.workers} process(es) × {setup.threads} thread(s)")
    console.print(f"[bold]{oracle.spec}[/] (a bound, searched with the truth): "
                  f"{setup.seeds} seed(s) on {where}; cache {setup.cache.root}")
    try:
        with Progress(*progress_columns(), console=console, transient=False) as bar:
            task = bar.add_task(oracle.spec, total=None)

            def round_(text: str) -> None:
                bar.update(task, description=text, completed=0, total=None)

            def report(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            outcome = run_oracle(setup.cfg.with_(delay=delay), oracle, setup.seed_list,
                                 cache=setup.cache, workers=setup.workers,
                                 threads_per_worker=setup.threads,
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


def _bound_doc(bound: Any, results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """What results.json says of one oracle bound: the search, its cost, and for every
    metric of :data:`OPTIMUM_METRICS` each policy's paired distance to it (bound − policy in
    the metric's better direction: positive where the bound is better), over the seeds both
    have."""
    from aoi3d.experiment.optimum import paired_difference, sign_of

    search, metric = bound.spec.split(":")[1:]
    minus: dict[str, dict[str, Any]] = {}
    for name in OPTIMUM_METRICS:
        sign = sign_of(name)

        def per_seed(rs: Sequence[EpisodeResult], name: str = name, sign: float = sign
                     ) -> dict[int, float]:
            return {r.seed: sign * getattr(r, name) for r in rs
                    if getattr(r, name) is not None}

        mine = per_seed(bound.results)
        by_policy: dict[str, list[EpisodeResult]] = {}
        for r in results:
            by_policy.setdefault(r.policy, []).append(r)
        minus[name] = {p: paired_difference(mine, per_seed(rs)).to_dict()
                       for p, rs in by_policy.items()}
    return {"kind": "bound", "search": search, "metric": metric,
            "note": "searched with the ground truth at each scored decision: a bound on "
                    "frame selection, not a policy a scheduler could run",
            "cost": bound.cost(), "minus": minus}


def _print_bound(bound: Any, doc: dict[str, Any]) -> None:
    cost = doc["cost"]
    per = cost["reconstructions_per_decision"]
    console.print(
        f"[bold]{bound.spec}[/] is a bound (searched with the truth), not a policy: "
        f"{cost['reconstructions']} reconstructions over {cost['decisions']} decisions "
        f"({per['mean']:.1f} per decision, {per['min']}–{per['max']}), "
        f"{cost['compute_s']:.0f} s of compute")
    table = Table(title=f"{bound.spec} − policy (paired; positive: the bound is better)")
    table.add_column("policy")
    for name in ("psnr_db", "psnr_dynamic_db", "reward"):
        table.add_column(name, justify="right")
    for p in doc["minus"]["psnr_db"]:
        table.add_row(short_label(p), *(fmt(doc["minus"][m][p]["mean"],
                                             doc["minus"][m][p]["ci95"],
                                             3 if m == "reward" else 2)
                                         for m in ("psnr_db", "psnr_dynamic_db", "reward")))
    console.print(table)
