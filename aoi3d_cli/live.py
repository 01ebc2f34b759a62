"""``aoi3d live``: drive and measure a running pipeline over its REST APIs.

``aoi3d live sweep`` sets each policy in turn on the scheduler (``PUT /policy``), resets the
model when asked (``POST /reset`` on the trainer), lets it settle, then collects the Quality
of the decisions taken during the measurement window (``GET /quality`` of the metrics
service, attributed to the policy by decision id: the ids of the window's first and last
decision, read from ``GET /decision``) and the cameras the decisions used (``GET /decision``
sampled through the window). It writes CSV, JSON and a PNG like ``aoi3d experiment
tradeoff`` and, unless ``--no-sim``, overlays the virtual-clock curve of the same scene,
channel, carry mode and training budget per rendered decision, with the sim-to-live
difference per policy.

The REST client and the pipeline's process are :mod:`aoi3d_cli.livehttp`'s; the statistics,
the virtual clock, the figures and the files are the domain's (:mod:`aoi3d.live`). Those
modules load httpx, scipy, torch and matplotlib, so the command imports them in its body:
``aoi3d --help`` stays fast (tests/unit/cli/test_cli_startup.py).
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from aoi3d.metric import (
    BY_NAME,
    LPIPS,
    PSNR,
    PSNR_DISPLAY,
    PSNR_DYNAMIC,
    PSNR_DYNAMIC_DISPLAY,
    REWARD,
    SSIM,
)
from aoi3d_cli.common import fmt, make_console
from services.kit.ports import REST_FIRST, REST_LAST, ZENOH_PORT

if TYPE_CHECKING:
    from aoi3d.live.report import LiveSweep
    from aoi3d.live.sim import PoolTwin
    from aoi3d.live.summary import Measurement
    from aoi3d_cli.livehttp import LiveSession, SweepWindows

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="Drive and measure the running pipeline.")
console = make_console(stderr=True)  # progress; the results go to stdout


# --- the command ---------------------------------------------------------------------------
@app.command()
def sweep(
    policies: Annotated[str, typer.Option(
        help="Policies to measure, comma-separated, from the freshest to the stalest (the "
             "ends of the list are the ends of the curve).")]
    = "mat:40,mat:70,mat:130,all",
    settle_s: Annotated[float, typer.Option(
        min=0, help="Wall seconds after setting a policy (and resetting) before measuring.")]
    = 10.0,
    measure_s: Annotated[float, typer.Option(
        min=1, help="Wall seconds of decisions measured per policy and repeat.")] = 90.0,
    repeats: Annotated[int, typer.Option(
        min=1, help="Passes over the policies (interleaved, so drift hits every policy).")] = 2,
    reset_each: Annotated[bool, typer.Option(
        help="POST /reset on the dispatcher after each policy change.")] = True,
    url_base: Annotated[str, typer.Option(help="Scheme and host of the services.")]
    = "http://127.0.0.1",
    port_offset: Annotated[int, typer.Option(
        help=f"Added to the services' default ports {REST_FIRST}..{REST_LAST}.")] = 0,
    site: Annotated[str | None, typer.Option(
        help="The site to measure (its policy, decisions and quality, /sites/<site>/…) while "
             "the run's other sites go on; default: the run's first site.")] = None,
    out: Annotated[Path, typer.Option(help="Output folder (CSV, JSON, PNG).")]
    = Path("runs/live/sweep"),
    json_: Annotated[bool, typer.Option(
        "--json", help="Print one JSON object (the results) on stdout.")] = False,
    up: Annotated[bool, typer.Option(
        help="Start a pipeline (aoi3d up) for the sweep and stop it afterwards.")] = False,
    zenoh_port: Annotated[int, typer.Option(help="Zenoh port of the pipeline --up starts.")]
    = ZENOH_PORT,
    time_scale: Annotated[float, typer.Option(
        help="Time scale of the pipeline --up starts.")] = 0.1,
    workers: Annotated[int, typer.Option(
        min=1, help="Reconstruction workers of the pipeline --up starts.")] = 1,
    sim: Annotated[bool, typer.Option(
        help="Overlay the virtual-clock curve (same scene, channel, carry, budget).")] = True,
    sim_pool: Annotated[bool, typer.Option(
        help="Run the virtual clock through the twin of the live pool (fresh and stream "
             "carries): the pipeline's workers and time scale, each job charged the workers' "
             "own median job time for its steps and frames (the dispatcher's GET /status job_s), "
             "the rest superseded; --no-sim-pool: every fifth decision rendered, no queue.")]
    = True,
    delay: Annotated[str | None, typer.Option(
        help="The channel for the sweep (PUT /channel on the network service before measuring; "
             "the one in force is put back afterwards): a delay spec (exp:60, …) or a channel "
             "that changes — regimes:SPEC@DUR,… (e.g. regimes:exp:20@10s,exp:200@10s), "
             "trace:PATH[,offset=MS][,spread=MS][,scale=S] (a mahimahi uplink trace; the path "
             "as the network service reads it), cell:PATH[,…]. Default: leave the channel as "
             "it is.")] = None,
    sim_seeds: Annotated[int, typer.Option(
        min=1, help="Virtual-clock seeds per policy (4 scored renders each; 4 seeds proved "
                    "too few to compare with a live run, see docs/research.md).")] = 16,
    sim_seed_offset: Annotated[int, typer.Option(
        min=0, help="First virtual-clock seed (default: away from the seeds 0..9 the "
                    "experiments were developed on).")] = 1000,
    dataset: Annotated[Path, typer.Option(
        help="The pipeline's scene dataset (for the virtual clock and the truth beside the "
             "renders; with --up, the pipeline's).")]
    = Path("data/turbine-rotor"),
    cache: Annotated[Path, typer.Option(help="Episode cache of the virtual clock.")]
    = Path("runs/experiments/cache"),
    timeout_s: Annotated[float, typer.Option(
        min=1, help="Timeout of each REST call and of each wait for the pipeline.")] = 30.0,
    backends: Annotated[str | None, typer.Option(
        help="Fields to sweep in one run, comma-separated (e.g. grid,flow: the static grid "
             "beside the time-aware field, rendered at the display time): PUT /backend on the "
             "dispatcher before each one's policies (the one in force is put back afterwards); "
             "each writes its results under OUT/<backend>/, and a last table sets their "
             "display-time PSNR side by side. Default: the dispatcher's backend as it is.")]
    = None,
) -> None:
    """Measure each policy on the running pipeline; write CSV, JSON and a PNG with the
    virtual clock's curve beside the live one. PSNR is reported at the decision's time and at
    display time (against the truth when the render was ready: what a viewer saw).

    Reports, per metric, whether the best policy is an interior maximum beyond its 95%
    confidence interval: neither end of --policies, and the Welch (unpaired: the windows are
    different renders, not seeds) 95% CI of best − each end above zero."""
    specs, bodies, canon, delay = _checked(policies, delay, site)
    fields = _checked_backends(backends)
    from aoi3d_cli.livehttp import LiveSession

    started = time.monotonic()
    docs: dict[str, dict[str, Any]] = {}
    settings = {"settle_s": settle_s, "measure_s": measure_s, "repeats": repeats,
                "reset_each": reset_each, "port_offset": port_offset, "site": site,
                "sim_pool": sim_pool}
    with LiveSession.on(console, url_base, port_offset, zenoh_port, site, timeout_s) as session:
        if up:
            session.start_pipeline(time_scale, f"live-sweep-{os.getpid()}",
                                   ["--dataset", str(dataset), "--workers", str(workers)])
        runs: list[str | None] = [*fields] or [None]  # None: the dispatcher's backend as it is
        measured: list[tuple[str | None, SweepWindows, float]] = []
        with _backends_put_back(session, fields):
            for field in runs:
                t_field = started if not measured else time.monotonic()
                if field is not None:
                    _put_backend(session, field)
                windows = session.measure(specs, bodies, canon, delay=delay,
                                          settle_s=settle_s, measure_s=measure_s,
                                          repeats=repeats, reset_each=reset_each)
                measured.append((field, windows, time.monotonic() - t_field))
    # the virtual clock runs once the live windows are in (and a pipeline --up started has
    # stopped): it does not take the pipeline's cores while it is measured
    for field, windows, live_wall_s in measured:
        docs[field or ""] = _report(
            windows, [canon[s] for s in specs], live_wall_s, out / field if field else out,
            sim=sim, sim_seeds=sim_seeds, sim_seed_offset=sim_seed_offset, dataset=dataset,
            cache=cache, settings=settings, show="none" if fields and json_ else
            "json" if json_ else "table")
    if fields:
        _side_by_side(docs, out, json_)


def _checked_backends(backends: str | None) -> list[str]:
    """--backends: the fields to sweep, each one aoi3d knows (none: the dispatcher's as it is)."""
    from aoi3d.field import UnknownBackendError, check_backend

    fields = [b.strip() for b in (backends or "").split(",") if b.strip()]
    try:
        for b in fields:
            check_backend(b)
    except UnknownBackendError as err:
        raise typer.BadParameter(str(err), param_hint="'--backends'") from None
    return fields


def _put_backend(session: LiveSession, field: str) -> None:
    from aoi3d_cli.livehttp import LiveError

    console.print(f"backend: {escape(field)}")
    try:
        session.pipe.call("PUT", "dispatcher", "/backend", json={"backend": field})
    except LiveError as err:
        console.print(f"[red]error:[/] {escape(str(err))}")
        raise typer.Exit(1) from None


@contextlib.contextmanager
def _backends_put_back(session: LiveSession, fields: list[str]) -> Iterator[None]:
    """While sweeping ``fields``: afterwards the dispatcher's backend is the one it had (on a
    pipeline this sweep did not start)."""
    from aoi3d_cli.livehttp import LiveError

    before = session.pipe.call("GET", "dispatcher", "/status").get("backend") if fields else None
    try:
        yield
    finally:
        if before is not None and session.proc is None:
            try:
                session.pipe.call("PUT", "dispatcher", "/backend", json={"backend": before})
            except LiveError as err:
                console.print(f"[yellow]could not put the backend back:[/] {escape(str(err))}")


def _report(windows: SweepWindows, order: list[str], live_wall_s: float, out: Path, *, sim: bool,
            sim_seeds: int, sim_seed_offset: int, dataset: Path, cache: Path,
            settings: dict[str, Any], show: str) -> dict[str, Any]:
    """One backend's sweep: the virtual clock beside it, the files, on stdout ``show``
    (``table``, ``json``, or ``none``: a --backends --json sweep prints one document at the
    end); returns the results document."""
    from aoi3d.live.figures import plot
    from aoi3d.live.report import LiveSweep

    measure_s, repeats = settings["measure_s"], settings["repeats"]
    started = time.monotonic()
    status1, channel = windows.status1, windows.channel
    carry = status1.get("carry", "warm")
    render_steps = int(status1.get("render_steps") or 0)
    steps_per_s = float(status1.get("steps_per_s") or 0.0)
    sim_doc = (_virtual_clock(order, windows, dataset=dataset, seeds=sim_seeds,
                              seed_offset=sim_seed_offset, cache=cache,
                              pool=settings["sim_pool"]) if sim else None)
    result = LiveSweep.of(windows.measurements, order, sim=sim_doc, settings={
        "policies": order, **settings, "carry": carry, "render_steps": render_steps,
        "trainer_steps_per_s": steps_per_s, "channel": channel,
        "backend": status1.get("backend")})
    doc = result.document({"live": live_wall_s,
                           "total": live_wall_s + time.monotonic() - started})
    result.write(out, doc)
    plot(result.results, sim_doc, out / "live_sweep.png",
         f"Live sweep — {channel['delay']}, carry {carry}, {render_steps} steps per rendered "
         f"decision, {steps_per_s:.0f} training steps/s, {measure_s:g} s × {repeats} per policy")
    _views_figure(windows.measurements, dataset, out)
    if show == "json":
        print(json.dumps({k: doc[k] for k in ("results", "unpaired_interior_maximum",
                                               "settings", "wall_s")}, default=str))
    elif show == "table":
        stdout = make_console(width=160)
        stdout.print(_table(result))
        for v in result.verdicts():
            stdout.print(f"{v.metric}: best {escape(v.best)} ({v.best_mean:.3f}): {v.text}")
        stdout.print(f"results in {escape(str(out))}")
    return doc


def _side_by_side(docs: dict[str, dict[str, Any]], out: Path, json_: bool) -> None:
    """The backends of one sweep side by side: per policy, PSNR at decision and at display
    time, whole image and dynamic region (mean ± 95% CI per render); ``OUT/backends.json``."""
    from aoi3d.metric import PSNR, PSNR_DISPLAY, PSNR_DYNAMIC, PSNR_DYNAMIC_DISPLAY, names_of

    metrics = names_of((PSNR, PSNR_DYNAMIC, PSNR_DISPLAY, PSNR_DYNAMIC_DISPLAY))
    rows = [{"backend": b, "policy": r["policy"], "n": r["n"],
             **{m: r.get(m, {}) for m in metrics}}
            for b, doc in docs.items() for r in doc["results"]]
    out.mkdir(parents=True, exist_ok=True)
    (out / "backends.json").write_text(json.dumps({"rows": rows}, indent=2, default=str) + "\n")
    if json_:
        print(json.dumps({"backends": rows}, default=str))
        return
    table = Table(title="the backends side by side (mean ± 95% CI per render)")
    for c in ("backend", "policy", "n", "PSNR", "dyn. PSNR", "PSNR @display", "dyn. @display"):
        table.add_column(c, justify="right")
    for r in rows:
        table.add_row(escape(r["backend"]), escape(r["policy"]), str(r["n"]),
                      *(fmt(r[m].get("mean"), r[m].get("ci95"), 2) for m in metrics))
    stdout = make_console(width=160)
    stdout.print(table)
    stdout.print(f"results in {escape(str(out))}/<backend>/, "
                 f"{escape(str(out / 'backends.json'))}")


def _virtual_clock(order: list[str], windows: SweepWindows, *, dataset: Path, seeds: int,
                   seed_offset: int, cache: Path, pool: bool = True) -> dict[str, Any] | None:
    """The virtual clock's run of ``order`` with the live dispatcher's carry, budget and channel
    — and with ``pool``, the twin of the live pool: the run's workers, time scale and the
    workers' own job times (None, with a line saying why, when it cannot run them: the live
    measurement is kept)."""
    from aoi3d.live import steps_per_decision
    from aoi3d.live.sim import SimRefused, simulate

    status1, channel = windows.status1, windows.channel
    carry = status1.get("carry", "warm")
    render_steps = int(status1.get("render_steps") or 0)
    backend = status1.get("backend") or "grid"
    twin = _pool_twin(status1, backend, carry) if pool else None
    console.print(f"virtual clock: {seeds} seed(s) per policy, carry {carry}, "
                  f"{render_steps} steps per rendered decision, delay {channel['delay']}"
                  + (f", the pool's twin: {twin.workers} worker(s) at time scale "
                     f"{twin.time_scale:g}, {len(twin.job_ms)} timed (steps, frames) "
                     f"cells, else {twin.fixed_ms:.1f} + {twin.step_ms:.2f} ms/step"
                     if twin is not None else ", no pool"))
    try:  # its _config holds the twin's settings (pool_workers, time_scale, compute_*)
        return simulate(order, dataset=dataset, delay=channel["delay"], carry=carry,
                       steps_per_decision=steps_per_decision(
                           windows.status0, status1, windows.measurements),
                       render_steps=render_steps, cold_steps=_cold_steps(status1),
                       seeds=seeds, seed_offset=seed_offset, cache=cache, processes=None,
                       backend=backend, pool=twin)
    except SimRefused as err:
        console.print(f"no virtual clock: {escape(str(err))}")
        return None


def _pool_twin(status: dict[str, Any], backend: str, carry: str) -> PoolTwin | None:
    """The live pool as the twin runs it, from the dispatcher's status: its workers, time scale
    and job times; None (and a line why) when the status cannot say."""
    from aoi3d.experiment.config import POOL_CARRIES
    from aoi3d.live.sim import PoolTwin, job_cost, job_table

    workers = len((status.get("pool") or {}).get("workers") or [])
    cost = job_cost(status.get("job_s") or {}, backend, carry)
    if carry not in POOL_CARRIES or workers < 1 or cost is None:
        console.print(f"no pool in the virtual clock: carry {carry} (the twin runs "
                      f"{', '.join(POOL_CARRIES)}), {workers} worker(s), "
                      f"{'no' if cost is None else 'some'} timed job")
        return None
    return PoolTwin(workers, float(status.get("time_scale") or 1.0), *cost,
                    job_ms=job_table(status.get("job_s") or {}, backend, carry),
                    fresh_fraction=float((status.get("pool") or {}).get("fresh_fraction", 1.0)))


def _cold_steps(status: dict[str, Any]) -> int:
    """The stream carry's cold-start budget: its status's if it says, else the dispatcher's
    default (``AOI3D_DISPATCHER_COLD_STEPS``; the status does not report it)."""
    if status.get("cold_steps"):
        return int(status["cold_steps"])
    from services.dispatcher.settings import Settings

    return int(Settings.model_fields["cold_steps"].default)


def _checked(policies: str, delay: str | None, site: str | None
             ) -> tuple[list[str], dict[str, Any], dict[str, str], str | None]:
    """--policies (at least two: each one's PUT body and canonical spec), --delay (its
    canonical spec) and --site checked; a bad one is a usage error naming it."""
    specs = [s.strip() for s in policies.split(",") if s.strip()]
    if len(specs) < 2:
        raise typer.BadParameter("give at least two policies", param_hint="'--policies'")
    from aoi3d.channel import DelaySpecError, parse_channel
    from aoi3d.policy import parse_policy
    from aoi3d.sites import check_site

    try:
        bodies = {s: parse_policy(s).to_json() for s in specs}
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="'--policies'") from None
    if delay is not None:
        try:
            delay = parse_channel(delay).spec
        except DelaySpecError as err:
            raise typer.BadParameter(str(err), param_hint="'--delay'") from None
    canon = {s: parse_policy(s).spec for s in specs}
    if site is not None:
        try:
            check_site(site)
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="'--site'") from None
    return specs, bodies, canon, delay


def _views_figure(measurements: list[Measurement], dataset: Path, out: Path) -> None:
    """live_views.png: each policy's last render beside the truth of its time (when the
    dataset can be read for the truth; else a line says so and the sweep goes on)."""
    from aoi3d.live.figures import plot_views, view_pairs
    from aoi3d.scene import open_dataset

    pairs = view_pairs(measurements)
    if pairs:
        try:
            ds = open_dataset(dataset)
        except (OSError, ValueError) as err:  # the truth is only for this figure: say so, go on
            console.print("no views figure: cannot read the dataset for the truth "
                          f"({escape(str(err))})")
        else:
            plot_views(pairs, ds, out / "live_views.png",
                       "Live renders (top) and the truth of the same time (bottom), the last "
                       "render of each policy")


# the table's metric columns: each score, its display-time form beside it (what a viewer saw)
_SHOWN = ((PSNR.name, "PSNR (dB)"), (PSNR_DISPLAY.name, "display PSNR"),
          (PSNR_DYNAMIC.name, "dyn. PSNR"), (PSNR_DYNAMIC_DISPLAY.name, "dyn. display"),
          (SSIM.name, "SSIM"), (LPIPS.name, "LPIPS"), (REWARD.name, "reward"))


def _table(result: LiveSweep) -> Table:
    table = Table(title="live sweep (mean ± 95% CI per render)")
    cols = ["policy", "n", *(label for _, label in _SHOWN), "cameras", "AoI used (ms)"]
    if result.sim is not None:
        cols += ["sim PSNR", "live − sim (dB)", "sim display PSNR"]
    for c in cols:
        table.add_column(c, justify="right")

    def cell(stat: dict[str, Any], digits: int) -> str:
        return fmt(stat.get("mean"), stat.get("ci95"), digits)

    for r in result.results:
        cells = [escape(r["policy"]), str(r["n"]),
                 *(cell(r[m], BY_NAME[m].digits) for m, _ in _SHOWN),
                 cell(r["cameras_used"], 1), cell(r["aoi_used_ms"], 0)]
        if result.sim is not None:
            sim = result.sim.get(r["policy"], {})
            s = sim.get("psnr_db", {}).get("mean")
            live = r["psnr_db"]["mean"]
            cells += [fmt(s, None, 2),
                      "—" if s is None or live is None else f"{live - s:+.2f}",
                      fmt(sim.get("psnr_display_db", {}).get("mean"), None, 2)]
        table.add_row(*cells)
    return table
