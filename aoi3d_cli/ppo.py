"""``aoi3d ppo …``: train the single-step PPO frame-selection agent, evaluate it.

``train`` runs :func:`aoi3d.rl.train.train` (batches of one-step episodes of
``aoi3d/FrameSelection-v0`` on a pool of env processes, one PPO update per batch, checkpoints,
``episodes.csv``, ``updates.csv``, ``reward.png``, ``config.json``); ``eval`` scores a
checkpoint's deterministic policy — and, with ``--compare``, other policies on the same
episodes — on held-out seeds, with 95% confidence intervals (what it writes:
:class:`aoi3d.rl.report.EvalReport`). ``presets`` lists the budgets.

Torch, the agent and the experiment engine are imported inside the commands, so that
``aoi3d --help`` and the other commands start without them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.table import Table

from aoi3d.scene.framings import FRAMING_DATASETS
from aoi3d_cli.common import (
    LpipsOpt,
    ProcessesOpt,
    ThreadsOpt,
    episode_config,
    fmt,
    make_console,
    open_experiment_dataset,
    parse_sets,
    progress_columns,
    short_label,
    with_shared_options,
)

if TYPE_CHECKING:
    from aoi3d.experiment import EpisodeConfig
    from aoi3d.rl.presets import PPOPreset, TrainConfig
    from aoi3d.rl.report import EvalReport
    from aoi3d.rl.train import TrainProgress, TrainSummary
    from aoi3d.scene import SceneDataset

PPO_PRESET_NAMES = ("quick", "paper")
"""The names of :data:`aoi3d.rl.presets.PPO_PRESETS`, for ``--help`` without importing torch
(a test keeps them equal)."""

app = typer.Typer(no_args_is_help=True, add_completion=False)
console = make_console()


@app.callback()
def ppo() -> None:
    """Single-step PPO over the AoI vector: train, evaluate."""


PresetOpt = Annotated[str, typer.Option(
    help=f"PPO budget preset: {', '.join(PPO_PRESET_NAMES)} (`aoi3d ppo presets` shows them).")]
DatasetOpt = Annotated[Path | None, typer.Option(
    help="Scene dataset (default: the preset's, the experiments' scene at "
         f"{FRAMING_DATASETS['rotor']}, generated if missing).")]
StepsOpt = Annotated[int | None, typer.Option(
    min=1, help="Radiance-field training steps per episode (default: the preset's).")]
CacheOpt = Annotated[Path | None, typer.Option(
    help="Result cache of (seed, selection, budget) episodes, shared between runs. "
         "Default: runs/ppo/cache.")]
NoCacheOpt = Annotated[bool, typer.Option(
    "--no-cache", help="Compute every episode (no result cache).")]
DeviceOpt = Annotated[str | None, typer.Option(
    help="Torch device of the radiance field: cpu or cuda (default: the preset's, cpu). "
         "The agent itself is a tiny MLP and runs on the CPU.")]
SetOpt = Annotated[list[str] | None, typer.Option(
    "--set", help="Override an episode config field, KEY=VALUE (JSON where it parses), "
                  "e.g. --set delay=exp:40.")]


def _shared_options(
    dataset: DatasetOpt = None,
    steps_per_epoch: StepsOpt = None,
    processes: ProcessesOpt = None,
    threads: ThreadsOpt = 1,
    cache: CacheOpt = None,
    no_cache: NoCacheOpt = False,
    device: DeviceOpt = None,
    lpips: LpipsOpt = True,
    set_: SetOpt = None,
) -> None:
    """The options ``train`` and ``eval`` take after their own (a signature only:
    :func:`aoi3d_cli.common.with_shared_options`)."""


@dataclass(frozen=True)
class _Shared:
    """The values of :func:`_shared_options` for one invocation."""

    dataset: Path | None
    steps_per_epoch: int | None
    processes: int | None
    threads: int
    cache: Path | None
    no_cache: bool
    device: str | None
    lpips: bool
    set_: list[str] | None

    def episode_config(self, base: EpisodeConfig) -> EpisodeConfig:
        """``base`` with these options applied (:func:`aoi3d_cli.common.episode_config`)."""
        changes: dict[str, Any] = {"lpips": self.lpips}
        if self.dataset is not None:
            changes["dataset"] = str(self.dataset)
        if self.steps_per_epoch is not None:
            changes["steps_per_epoch"] = self.steps_per_epoch
        if self.device is not None:
            changes["device"] = self.device
        return episode_config(base, changes, self.set_)

    @property
    def cache_dir(self) -> Path | None:
        """The result cache: none with ``--no-cache``, else ``--cache`` or runs/ppo/cache."""
        if self.no_cache:
            return None
        return self.cache if self.cache is not None else Path("runs/ppo/cache")

    @property
    def n_processes(self) -> int:
        from aoi3d.experiment import default_processes

        return self.processes if self.processes is not None else default_processes()


@app.command()
def presets() -> None:
    """List the PPO presets."""
    from aoi3d.rl.presets import PPO_PRESETS

    table = Table(title="PPO presets")
    for name in ("preset", "episodes", "batch", "steps/episode", "delay", "eval seeds", "note"):
        table.add_column(name)
    for p in PPO_PRESETS.values():
        table.add_row(p.name, str(p.episodes), str(p.batch_size),
                      str(p.episode.steps_per_epoch), p.episode.delay, str(p.eval_seeds), p.note)
    console.print(table)


RewardOpt = Annotated[str, typer.Option(
    help="The reward learned: reward (at the decision's time) or reward_display (at display "
         "time, once the render's compute is done: what a viewer sees).")]
BudgetsOpt = Annotated[str | None, typer.Option(
    help="Budgets (training steps per render, comma-separated, e.g. 25,50,100) each episode's "
         "render is drawn from, so the lag to the display varies. Default: the preset's "
         "steps.")]
ObserveLagOpt = Annotated[bool, typer.Option(
    "--observe-lag", help="The agent also observes the expected lag from the decision to its "
                          "display (at the episode's budget).")]


@app.command("train")
@with_shared_options(_shared_options, _Shared)
def train_cmd(
    shared: _Shared,
    preset: PresetOpt = "quick",
    episodes: Annotated[int | None, typer.Option(
        min=1, help="Training episodes (default: the preset's, 600).")] = None,
    batch_size: Annotated[int | None, typer.Option(
        min=1, help="Episodes per PPO update (default: the preset's).")] = None,
    out: Annotated[Path | None, typer.Option(
        help="Output folder (checkpoints, CSV, plot). Default: runs/ppo/<preset>.")] = None,
    resume: Annotated[bool, typer.Option(
        help="Continue from <out>/checkpoint.pt (same options; --episodes may grow).")]
    = False,
    lr: Annotated[float | None, typer.Option(help="Adam step size.")] = None,
    clip_eps: Annotated[float | None, typer.Option(help="PPO clip ε.")] = None,
    seed: Annotated[int | None, typer.Option(
        min=0, help="Agent seed (weights, sampled actions, minibatches).")] = None,
    seed_offset: Annotated[int, typer.Option(
        min=0, help="Training episode i uses channel seed 100,000 + OFFSET + i (another "
                    "training set of episodes; always below the held-out seeds).")] = 0,
    ppo_set: Annotated[list[str] | None, typer.Option(
        "--ppo-set", help="Override a PPOConfig field, KEY=VALUE (e.g. ent_coef=0.0).")]
    = None,
    checkpoint_every: Annotated[int, typer.Option(
        min=1, help="PPO updates between two checkpoints.")] = 5,
    features: Annotated[list[str] | None, typer.Option(
        "--features", help="What the agent observes of each camera besides its AoI "
                           "(repeatable): pose = its angle and distance to the held-out view, "
                           "fixed per rig and stored in the checkpoint. Default: the AoI "
                           "vector alone.")] = None,
    reward: RewardOpt = "reward",
    budgets: BudgetsOpt = None,
    observe_lag: ObserveLagOpt = False,
) -> None:
    """Train the agent (the paper's Fig. 7: reward per episode, in reward.png)."""
    from aoi3d.policy.ppo import PPOConfig
    from aoi3d.rl.presets import TrainConfig, get_ppo_preset

    try:
        chosen = get_ppo_preset(preset)
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="'--preset'") from None
    episode = shared.episode_config(chosen.episode)
    ds = open_experiment_dataset(Path(episode.dataset), console)
    n = episode.n_cameras or len(ds.train_ids)
    hyper: dict[str, Any] = {**dict(chosen.ppo), **parse_sets(ppo_set, "--ppo-set")}
    for key, value in (("lr", lr), ("clip_eps", clip_eps), ("seed", seed),
                       ("lag", observe_lag or None)):
        if value is not None:
            hyper[key] = value
    if features:
        hyper.update(_camera_features(features, episode, ds))
    try:
        ppo_cfg = PPOConfig.from_dict({**hyper, "n_cameras": n})
        cfg = TrainConfig(episode=episode, ppo=ppo_cfg,
                          episodes=episodes if episodes is not None else chosen.episodes,
                          batch_size=batch_size if batch_size is not None else chosen.batch_size,
                          checkpoint_every=checkpoint_every, preset=chosen.name,
                          seed_offset=seed_offset, reward=reward,
                          budgets=_budgets(budgets))
    except (TypeError, ValueError) as err:
        raise typer.BadParameter(str(err)) from None
    folder = out if out is not None else Path("runs/ppo") / chosen.name
    n_processes, threads, cache_dir = shared.n_processes, shared.threads, shared.cache_dir
    console.print(f"[bold]PPO training[/]: {cfg.episodes} episodes in batches of "
                  f"{cfg.batch_size}, {episode.steps_per_epoch} field steps each, on "
                  f"{n_processes} process(es) × {threads} thread(s); out {folder}; cache "
                  f"{cache_dir or 'off'}")
    summary = _train_with_progress(cfg, folder, ds, n_processes, threads, cache_dir, resume)
    console.print(
        f"{summary.episodes} episodes, {summary.updates} updates in {summary.wall_s:.0f} s "
        f"({summary.computed} computed, {summary.cached} from the cache); mean reward "
        f"{summary.reward_first:.4f} (first episodes) → {summary.reward_last:.4f} (last)")
    console.print(f"files in {folder}: {', '.join(summary.files)}")


def _budgets(text: str | None) -> tuple[int, ...]:
    """--budgets: comma-separated training steps (empty: none)."""
    try:
        return tuple(int(b) for b in text.split(",")) if text else ()
    except ValueError:
        raise typer.BadParameter(f"budgets must be whole numbers of steps, comma-separated, "
                                 f"got {text!r}", param_hint="'--budgets'") from None


def _camera_features(features: list[str], episode: EpisodeConfig, ds: SceneDataset
                     ) -> dict[str, Any]:
    """--features (known ones, each once) and their values for this rig's cameras."""
    from aoi3d.experiment.episode import train_ids
    from aoi3d.policy.ppo.obs import CAMERA_FEATURES
    from aoi3d.rl.train import camera_feature_values

    unknown = sorted(set(features) - set(CAMERA_FEATURES))
    if unknown:
        raise typer.BadParameter(f"unknown camera feature(s) {unknown}; known: "
                                 f"{sorted(CAMERA_FEATURES)}", param_hint="'--features'")
    names = tuple(dict.fromkeys(features))
    return {"features": names,
            "camera_features": camera_feature_values(names, ds, train_ids(episode, ds))}


def _train_with_progress(cfg: TrainConfig, folder: Path, ds: SceneDataset, n_processes: int,
                         threads: int, cache_dir: Path | None, resume: bool) -> TrainSummary:
    """:func:`aoi3d.rl.train.train` with a progress bar; its refusals as usage errors, and
    Ctrl-C says where the last checkpoint is (exit status 130)."""
    from rich.progress import Progress

    from aoi3d.rl.train import train

    try:
        with Progress(*progress_columns(), console=console, transient=False) as bar:
            task = bar.add_task("episodes", total=cfg.episodes)

            def report(p: TrainProgress) -> None:
                text = f"update {p.updates}"
                if p.moving_reward is not None:
                    text += f", reward (moving avg) {p.moving_reward:.3f}"
                bar.update(task, completed=p.done, description=text)

            return train(cfg, folder, dataset=ds, processes=n_processes, threads=threads,
                         cache=cache_dir, resume=resume, progress=report)
    except FileExistsError as err:
        raise typer.BadParameter(f"{err}", param_hint="'--out' / '--resume'") from None
    except FileNotFoundError as err:
        raise typer.BadParameter(str(err), param_hint="'--resume'") from None
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None
    except KeyboardInterrupt:
        console.print(f"[yellow]interrupted[/]: the last checkpoint is in {folder}; run the "
                      "same command with --resume to continue")
        raise typer.Exit(130) from None


@app.command("eval")
@with_shared_options(_shared_options, _Shared)
def eval_cmd(
    shared: _Shared,
    checkpoint: Annotated[Path, typer.Option(help="A checkpoint of `aoi3d ppo train`.")],
    seeds: Annotated[int | None, typer.Option(
        min=1, help="Held-out episodes (seeds from 1,000,000 on; never a training seed). "
                    "Default: the preset's.")] = None,
    seed_offset: Annotated[int, typer.Option(
        min=0, help="Skip this many held-out seeds: seeds 1,000,000 + OFFSET + k (another "
                    "held-out set; 0–39 were used while developing).")] = 0,
    compare: Annotated[list[str] | None, typer.Option(
        "--compare", help="Also score this policy on the same episodes (repeat), e.g. "
                          "all, mat:100, freshest:9.")] = None,
    preset: Annotated[str | None, typer.Option(
        help="Take the episode config from this PPO preset instead of the checkpoint's.")]
    = None,
    out: Annotated[Path | None, typer.Option(
        help="Output folder (default: <checkpoint folder>/eval).")] = None,
) -> None:
    """Mean PSNR/SSIM/LPIPS/reward (95% CI) of the checkpoint's deterministic policy on
    held-out seeds; writes eval.csv, eval_summary.csv and eval.json."""
    from rich.progress import Progress

    from aoi3d.policy import PolicySpecError
    from aoi3d.policy.ppo.actor import Actor
    from aoi3d.rl.evaluate import evaluate
    from aoi3d.rl.presets import eval_seeds
    from aoi3d.rl.report import EvalReport

    started = time.time()
    try:
        agent, extra = Actor.load_with_extra(checkpoint)
    except (FileNotFoundError, ValueError) as err:
        raise typer.BadParameter(str(err), param_hint="'--checkpoint'") from None
    base, chosen = _eval_base(preset, extra)
    episode = shared.episode_config(base)
    count = seeds if seeds is not None else (chosen.eval_seeds if chosen else 40)
    seed_list = eval_seeds(count, seed_offset)
    ds = open_experiment_dataset(Path(episode.dataset), console)
    specs = [f"ppo:{checkpoint}", *(compare or [])]
    folder = out if out is not None else checkpoint.parent / "eval"
    folder.mkdir(parents=True, exist_ok=True)
    n_processes = shared.n_processes
    console.print(f"[bold]PPO evaluation[/]: {len(specs)} policies × {count} held-out seeds "
                  f"({seed_list[0]}…{seed_list[-1]}), {episode.steps_per_epoch} field steps "
                  f"per episode, {n_processes} process(es)")
    try:
        with Progress(*progress_columns(), console=console, transient=False) as bar:
            task = bar.add_task("episodes", total=len(specs) * count)
            outcome = evaluate(
                specs, episode, seed_list, dataset=ds, processes=n_processes,
                threads=shared.threads, cache=shared.cache_dir,
                aoi_scale_ms=agent.config.aoi_scale_ms,
                progress=lambda done, total: bar.update(task, completed=done, total=total))
    except PolicySpecError as err:
        raise typer.BadParameter(str(err), param_hint="'--compare'") from None
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None
    report = EvalReport.of(outcome, checkpoint=checkpoint, specs=specs, seeds=seed_list,
                           seed_offset=seed_offset, episode=episode, extra=extra,
                           started=started)
    report.write(folder)
    _print_eval(report, outcome.summary, count, episode.steps_per_epoch)
    console.print(f"results in {folder}")


def _eval_base(preset: str | None, extra: dict[str, Any]
               ) -> tuple[EpisodeConfig, PPOPreset | None]:
    """The episode config to evaluate on — --preset's, else the checkpoint's (else the quick
    preset's) — and the preset it came from, if any (its number of held-out seeds)."""
    from aoi3d.experiment import EpisodeConfig
    from aoi3d.rl.presets import PPO_PRESETS, get_ppo_preset

    chosen = None
    if preset is not None or "episode_config" not in extra:
        try:
            chosen = get_ppo_preset(preset or "quick")
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="'--preset'") from None
        base = chosen.episode
    else:
        base = EpisodeConfig.from_dict(dict(extra["episode_config"]))
        name = extra.get("preset")
        chosen = PPO_PRESETS.get(name) if isinstance(name, str) else None
    return base, chosen


def _print_eval(report: EvalReport, summary: list[dict[str, Any]], count: int,
                steps_per_epoch: int) -> None:
    """The evaluation's table, each metric's optimum set and a note when the agent is scored
    at another budget than it was trained at."""
    trained = report.trained_steps
    table = Table(title=f"held-out seeds: mean ± 95% CI over {count} episodes")
    for name in ("policy", "reward", "PSNR (dB)", "SSIM", "LPIPS", "cameras",
                 "Δ reward (PPO − this)"):
        table.add_column(name, justify="right")
    for r in summary:
        table.add_row(short_label(r["policy"]), fmt(r["reward"], r["reward_ci95"], 4),
                      fmt(r["psnr"], r["psnr_ci95"], 2), fmt(r["ssim"], r["ssim_ci95"], 3),
                      fmt(r["lpips"], r["lpips_ci95"], 3), fmt(r["n_selected"], None, 1),
                      fmt(r.get("first_minus_this_reward"),
                          r.get("first_minus_this_reward_ci95"), 4))
    console.print(table)
    for metric, opt in report.optima.items():
        console.print(f"{metric}: best {short_label(opt.best)}; not significantly worse "
                      f"(paired, {len(opt.seeds)} seeds): "
                      f"{', '.join(short_label(m) for m in opt.members)}")
    if trained is not None and trained != steps_per_epoch:
        console.print(f"[yellow]note[/]: the agent was trained at {trained} field steps per "
                      f"episode and is scored at {steps_per_epoch}; compare policies "
                      "at the budget the agent was trained for")
