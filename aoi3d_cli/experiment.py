"""``aoi3d experiment …``: the paper's tradeoff figures, each with one command.

Every command runs a sweep of episodes (:mod:`aoi3d.experiment`) on all local cores (or a
Ray cluster with ``--ray-address``), caches each episode under ``--cache`` (an interrupted
sweep resumes; a re-run computes only what is missing; commands share episodes), and writes
CSV, JSON (with the full config, the code version and the machine) and PNG figures to
``--out``. Each command parses its options, runs the sweep
(:mod:`aoi3d_cli.experiment_shared`), hands the results to the domain
(:mod:`aoi3d.experiment.tradeoff`, :mod:`~aoi3d.experiment.compare`,
:mod:`~aoi3d.experiment.report`, :mod:`~aoi3d.experiment.figures`) and prints the tables
(:mod:`aoi3d_cli.experiment_tables`).

The experiment engine (torch), the figures (matplotlib) and the channel (scipy) are imported
inside the commands, so that ``aoi3d --help`` and the other commands start without them.
"""

from __future__ import annotations

from typing import Annotated

import typer

from aoi3d_cli.common import short_label
from aoi3d_cli.experiment_shared import (
    Shared,
    console,
    experiment_command,
    run,
    run_oracle,
)
from aoi3d_cli.experiment_tables import (
    print_bound,
    print_delay_optima,
    print_optima,
    print_rows,
)

PRESET_NAMES = ("quick", "paper")
"""The names of :data:`aoi3d.experiment.PRESETS`, for ``--help`` without importing the engine
(a test keeps them equal)."""

app = typer.Typer(no_args_is_help=True, add_completion=False)


@app.callback()
def experiment() -> None:
    """Sweeps and figures of the timeliness–fidelity tradeoff on a virtual clock."""


PresetOpt = Annotated[str, typer.Option(
    help=f"Budget preset: {', '.join(PRESET_NAMES)} (quick: ≤ 10 min on 2 cores; paper: Γ every "
         "10 ms, 40 simulations per point).")]
DelayOpt = Annotated[str, typer.Option(help="Delay spec of the links, e.g. exp:60 (ms).")]


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


def _check_metric(metric: str, hint: str) -> None:
    from aoi3d.experiment.tradeoff import OPTIMUM_METRICS

    if metric not in OPTIMUM_METRICS:
        raise typer.BadParameter(f"unknown metric {metric!r}; accepted: "
                                 f"{', '.join(OPTIMUM_METRICS)}",
                                 param_hint=hint)


# --- commands --------------------------------------------------------------------------------
@app.command()
@experiment_command()
def tradeoff(
    shared: Shared,
    preset: PresetOpt = "quick",
    gammas: Annotated[str | None, typer.Option(
        help="MAT thresholds Γ in ms, comma-separated (default: the preset's).")] = None,
    delay: DelayOpt = "exp:60",
) -> None:
    """Fig. 4: PSNR, SSIM and LPIPS against the MAT Γ (mean of S simulations, 95% band),
    with the cameras used and the AoI of the used frames; `all` as the reference."""
    from aoi3d.channel import parse_channel
    from aoi3d.experiment.figures import plot_tradeoff
    from aoi3d.experiment.tradeoff import MatSweep, best_gamma, sweep_optima, tradeoff_rows

    setup = shared.setup("tradeoff", preset)
    gamma_list = _int_list(gammas, "'--gammas'") or setup.preset.gammas_ms
    delay = _delay(delay)
    sweep = MatSweep.of(gamma_list)
    outcome = run(setup, sweep.jobs([delay], setup.seed_list), "tradeoff")
    points, reference = tradeoff_rows(outcome.results, sweep)
    best = best_gamma(points)
    optima = sweep_optima(outcome.results, sweep=sweep)
    setup.write([outcome], {"gammas_ms": list(gamma_list), "delay": delay}, outcome.results,
                {"points.csv": points + ([reference] if reference else [])},
                best_gamma_ms=best, optimum={m: o.to_dict() for m, o in optima.items()},
                points=points, reference=reference)
    mean_y = parse_channel(delay).mean_ms
    plot_tradeoff(points, setup.out / "tradeoff.png", reference=reference, title=(
        f"Quality of the novel view vs MAT Γ — E[Y] = {mean_y:g} ms, "
        f"C = {setup.cfg.period_ms} ms, N = {setup.cfg.n_cameras or len(setup.dataset.train_ids)}, "
        f"S = {setup.seeds} (seeds {setup.seed_span}), {setup.cfg.carry} model, "
        f"{setup.cfg.steps_per_epoch} steps/decision"))
    print_rows(points + ([{"gamma_ms": "all", **reference}] if reference else []), "gamma_ms",
               f"tradeoff at {delay} (mean ± 95% CI over seeds {setup.seed_span})")
    print_optima(optima)
    console.print(f"results in {setup.out}")


@app.command()
@experiment_command(seeds=False)
def views(
    shared: Shared,
    preset: PresetOpt = "quick",
    gammas: Annotated[str | None, typer.Option(
        help="Γ values to show, comma-separated (default: the preset's).")] = None,
    rows: Annotated[int, typer.Option(min=1, help="Seeds shown, one row each.")] = 1,
    delay: DelayOpt = "exp:60",
) -> None:
    """Fig. 5: the novel view for several Γ (and `all`) next to the ground truth, at the last
    scored decision of an episode."""
    from aoi3d.experiment.figures import plot_views
    from aoi3d.experiment.tradeoff import MatSweep, view_grid

    setup = shared.setup("views", preset, seeds=rows)
    gamma_list = _int_list(gammas, "'--gammas'") or setup.preset.view_gammas_ms
    delay = _delay(delay)
    sweep = MatSweep.of(gamma_list)
    outcome = run(setup, sweep.jobs([delay], setup.seed_list), "views")
    grid, saved = view_grid(outcome, sweep, setup.seed_list, setup.dataset, setup.cache,
                            setup.out)
    setup.write([outcome], {"gammas_ms": list(gamma_list), "delay": delay, "rows": rows},
                outcome.results, {}, renders=saved)
    plot_views(grid, setup.out / "views.png", title=(
        f"Novel view (camera {setup.dataset.heldout_id}) vs MAT Γ at {delay}, "
        f"{setup.cfg.carry} model"))
    console.print(f"views in {setup.out / 'views.png'}")


@app.command("delay")
@experiment_command()
def delay_cmd(
    shared: Shared,
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
    from aoi3d.experiment.tradeoff import MatSweep, delay_optimum_row, tradeoff_rows

    _check_metric(metric, "'--metric'")
    setup = shared.setup("delay", preset)
    if shared.seeds is None:
        setup.seeds = setup.preset.delay_seeds
    delay_list = ([_delay(d, "'--delays'") for d in _spec_list(delays)]
                  if delays else list(setup.preset.delays))
    gamma_list = _int_list(gammas, "'--gammas'") or setup.preset.delay_gammas_ms
    sweep = MatSweep.of(gamma_list)
    jobs = [Job(label, d, s) for s in setup.seed_list for d in delay_list
            for label in sweep.policies if sweep.gamma(label) is not None]  # no reference
    outcome = run(setup, jobs, "delay")
    curves = []
    optima = []
    for d in delay_list:
        of_delay = [r for r in outcome.results if r.delay == d]
        points, _ = tradeoff_rows(of_delay, sweep)
        curves.extend(points)
        optima.append(delay_optimum_row(d, parse_channel(d).mean_ms, of_delay, points, sweep,
                                        metric))
    setup.write([outcome], {"delays": delay_list, "gammas_ms": list(gamma_list)},
                outcome.results, {"optima.csv": [{k: v for k, v in o.items() if k != "optimum"}
                                                 for o in optima], "curves.csv": curves},
                optima=optima, curves=curves)
    plot_delay(optima, curves, setup.out / "delay.png", metric=metric, title=(
        f"Optimal MAT Γ vs mean delay — C = {setup.cfg.period_ms} ms, S = {setup.seeds} "
        f"(seeds {setup.seed_span}), {setup.cfg.carry} model; bars: the optimum set"))
    print_delay_optima(optima, metric, setup.seed_span)
    console.print(f"results in {setup.out}")


@app.command()
@experiment_command()
def compare(
    shared: Shared,
    preset: PresetOpt = "quick",
    policy: Annotated[list[str] | None, typer.Option(
        "--policy", help="Policy spec (repeat): all, mat:<ms>, mat:best, freshest:<k>, "
                         "wait:<ms>, or any registered kind; a baseline of the follow-up "
                         "paper, tembed[:<features>[:<scale_ms>]] (timeliness embedding) or "
                         "wsum:<tau_ms> (weighted sum), each optionally @<policy> (default "
                         "@all); or the oracle bound, oracle[:rules|greedy|budgets[:<metric>]] "
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
    from aoi3d.experiment import EpisodeResult, Job
    from aoi3d.experiment.compare import CompareResult, CompareSpecError, plan_compare
    from aoi3d.experiment.figures import plot_compare
    from aoi3d.experiment.tradeoff import MatSweep, best_gamma, tradeoff_rows

    _check_metric(best_metric, "'--best-metric'")
    setup = shared.setup("compare", preset)
    delay = _delay(delay)
    specs = list(policy) if policy else list(setup.preset.compare)
    n_cameras = setup.cfg.n_cameras or len(setup.dataset.train_ids)
    try:  # every spec is checked before any sweep runs
        plan = plan_compare(specs, setup.cfg, n_cameras)
    except CompareSpecError as err:
        raise typer.BadParameter(str(err), param_hint="'--policy'") from None
    outcomes = []
    if plan.needs_best_gamma and mat_ms is None:
        mat_sweep = MatSweep.of(setup.preset.gammas_ms)
        sweep = run(setup, mat_sweep.jobs([delay], setup.seed_list), "tradeoff (for mat:best)")
        outcomes.append(sweep)
        mat_ms = best_gamma(tradeoff_rows(sweep.results, mat_sweep)[0], best_metric)
    resolved, as_json = plan.resolve(mat_ms)
    results: list[EpisodeResult] = []
    if resolved:
        outcome = run(setup, [Job(p, delay, s, trainer=t) for s in setup.seed_list
                              for t, p in resolved], "compare")
        outcomes.append(outcome)
        results = list(outcome.results)
    bounds = [run_oracle(setup, oracle, delay) for oracle in dict.fromkeys(plan.oracles)]
    result = CompareResult.of(results, bounds)
    setup.write(outcomes, {"policies": result.labels, "oracles": [b.spec for b in bounds],
                           "delay": delay, "mat_best_ms": mat_ms, "best_metric": best_metric},
                result.episodes, {"compare.csv": result.rows}, **result.document(as_json))
    plot_compare([{**r, "policy": short_label(r["policy"])} for r in result.rows],
                 setup.out / "compare.png", title=(
        f"Policies at {delay}, S = {setup.seeds} (the same seeds, {setup.seed_span}), "
        f"{setup.cfg.carry} model"))
    print_rows(result.rows, "policy",
               f"policies at {delay} (mean ± 95% CI over seeds {setup.seed_span})")
    print_optima(result.optima, unit="policy")
    for b in bounds:
        print_bound(b.spec, result.bound_docs[b.spec])
    console.print(f"results in {setup.out}")
