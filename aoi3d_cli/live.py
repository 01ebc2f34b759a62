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
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from aoi3d.ports import REST_FIRST, REST_LAST, SERVICE_PORTS, ZENOH_PORT, rest_port
from aoi3d_cli.common import fmt, make_console

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="Drive and measure the running pipeline.")
console = make_console(stderr=True)  # progress; the results go to stdout

METRICS = ("psnr_db", "psnr_dynamic_db", "ssim", "lpips", "reward")
"""Per-render quality fields summarised per policy (absent ones are reported as null)."""


class LiveError(RuntimeError):
    """The pipeline did not answer as expected; the message says what and where."""


# --- talking to the pipeline -----------------------------------------------------------------
@dataclass
class Pipeline:
    """The REST endpoints of a running pipeline."""

    url_base: str = "http://127.0.0.1"
    port_offset: int = 0
    timeout_s: float = 30.0
    site: str | None = None
    """The site measured (``/sites/<site>/…``); None: the run's first site (today's paths)."""
    client: Any = field(default=None, repr=False)

    RUN_LEVEL = frozenset({("trainer", "/reset"), ("trainer", "/backend"),
                           ("trainer", "/carry"), ("trainer", "/workers")})
    """Paths that are the run's, not a site's (the pool and its settings)."""

    def __post_init__(self) -> None:
        import httpx

        from aoi3d_cli.common import control_headers

        self.client = httpx.Client(timeout=self.timeout_s, headers=control_headers())

    def url(self, service: str, path: str) -> str:
        if self.site and (service, path) not in self.RUN_LEVEL and not path.startswith("/ready"):
            path = f"/sites/{self.site}{path}"
        return f"{self.url_base.rstrip('/')}:{rest_port(service, self.port_offset)}{path}"

    def call(self, method: str, service: str, path: str, **kw: Any) -> Any:
        import httpx

        url = self.url(service, path)
        try:
            resp = self.client.request(method, url, **kw)
        except httpx.HTTPError as err:
            raise LiveError(f"{method} {url}: {err!r} (is the pipeline up? `aoi3d up`, or "
                            f"pass --up)") from None
        if resp.status_code >= 400:
            raise LiveError(f"{method} {url} answered {resp.status_code}: {resp.text[:300]}")
        return resp.json()

    def ready(self) -> bool:
        import httpx

        try:
            return all(self.client.get(self.url(s, "/readyz")).status_code == 200
                       for s in SERVICE_PORTS)
        except httpx.HTTPError:
            return False

    def close(self) -> None:
        self.client.close()


@dataclass
class Measurement:
    """One policy's window: its Quality entries and the decisions sampled during it."""

    policy: str
    repeat: int
    first_decision: int
    last_decision: int
    wall_s: float
    qualities: list[dict[str, Any]]
    decisions: list[dict[str, Any]]
    render_png: bytes = b""
    render_decision: int | None = None


def _wait(what: str, check: Callable[[], Any], timeout_s: float, every_s: float = 0.25) -> Any:
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        try:
            last = check()
        except LiveError as err:
            last = err
        if last and not isinstance(last, Exception):
            return last
        time.sleep(every_s)
    raise LiveError(f"timed out after {timeout_s:g} s waiting for {what} (last: {last!r})")


def measure_policy(pipe: Pipeline, policy: dict[str, Any], spec: str, *, settle_s: float,
                   measure_s: float, reset: bool, repeat: int, sample_every_s: float = 0.5
                   ) -> Measurement:
    """Set ``policy``, (reset,) settle, and collect one measurement window."""
    pipe.call("PUT", "scheduler", "/policy", json=policy)
    _wait(f"a decision under {spec}",
          lambda: pipe.call("GET", "scheduler", "/decision").get("policy") == spec,
          pipe.timeout_s)
    if reset:
        pipe.call("POST", "trainer", "/reset")
    time.sleep(settle_s)
    first = pipe.call("GET", "scheduler", "/decision")
    if first["policy"] != spec:
        raise LiveError(f"the scheduler's policy changed under the sweep: {first['policy']!r} "
                        f"while measuring {spec!r}")
    decisions = [first]
    started = time.monotonic()
    while time.monotonic() - started < measure_s:
        time.sleep(sample_every_s)
        decisions.append(pipe.call("GET", "scheduler", "/decision"))
    last = decisions[-1]
    if last["policy"] != spec:
        raise LiveError(f"the scheduler's policy changed under the sweep: {last['policy']!r} "
                        f"while measuring {spec!r}")
    # the renders of the window's decisions come a render's compute later: wait for them
    lo, hi = first["decision_id"], last["decision_id"]
    png, png_decision = _latest_render(pipe)
    time.sleep(_render_latency_s(pipe))
    history = pipe.call("GET", "metrics", "/quality", params={"limit": 1000})["history"]
    qualities = [q for q in history if lo <= q["decision_id"] <= hi]
    return Measurement(policy=spec, repeat=repeat, first_decision=lo, last_decision=hi,
                       wall_s=time.monotonic() - started, qualities=qualities,
                       decisions=[d for d in decisions if d["policy"] == spec],
                       render_png=png, render_decision=png_decision)


def _latest_render(pipe: Pipeline) -> tuple[bytes, int | None]:
    """The trainer's latest render (PNG) and the decision it represents."""
    import httpx

    try:
        resp = pipe.client.get(pipe.url("trainer", "/render.png"))
    except httpx.HTTPError:
        return b"", None
    if resp.status_code != 200:
        return b"", None
    return resp.content, int(resp.headers.get("x-decision-id", "0"))


def _render_latency_s(pipe: Pipeline) -> float:
    """Wall seconds a render may take: its own training at the measured step rate, plus
    scoring; at least 2 s."""
    status = pipe.call("GET", "trainer", "/status")
    rate = status.get("steps_per_s") or 0.0
    steps = status.get("render_steps") or 0
    return max(2.0, 1.5 * steps / rate + 1.0 if rate > 0 else 2.0 + steps / 10.0)


def summarise(measurements: Sequence[Measurement], order: Sequence[str]) -> list[dict[str, Any]]:
    """One result per policy (in ``order``): per-render quality statistics and the cameras
    the window's decisions used."""
    from aoi3d.stats import mean_ci95

    out = []
    for spec in order:
        ms = [m for m in measurements if m.policy == spec]
        qs = [q for m in ms for q in m.qualities]
        ds = [d for m in ms for d in m.decisions]
        used = [len(d["selected"]) for d in ds]
        aoi = [float(sum(r["aoi_ms"] for r in d["selected"]) / len(d["selected"]))
               for d in ds if d["selected"]]
        row: dict[str, Any] = {"policy": spec, "n": len(qs)}
        for metric in METRICS:
            row[metric] = mean_ci95([q.get(metric) for q in qs]).to_dict()
        row["cameras_used"] = mean_ci95(used).to_dict()
        row["aoi_used_ms"] = mean_ci95(aoi).to_dict()
        row["render_views"] = mean_ci95([q.get("n_views") for q in qs]).to_dict()
        out.append(row)
    return out


# --- the virtual-clock counterpart -----------------------------------------------------------
def simulate(policies: Sequence[str], *, dataset: Path, delay: str, carry: str,
             steps_per_decision: int, render_steps: int, seeds: int, seed_offset: int,
             cache: Path, workers: int | None) -> dict[str, dict[str, Any]]:
    """The experiments' engine on the same scene, channel, carry and budget: per policy,
    ``{metric: {"mean", "ci95", "n"}}`` over ``seeds`` seeds."""
    from aoi3d.experiment.config import get_preset
    from aoi3d.experiment.sweep import Job, ResultCache, run_jobs
    from aoi3d.stats import mean_ci95

    base = get_preset("quick").episode
    changes: dict[str, Any] = {"dataset": str(dataset), "delay": delay, "carry": carry}
    if carry == "fresh":
        changes["steps_per_epoch"] = render_steps
    else:
        changes["steps_per_epoch"] = max(1, steps_per_decision)
        changes["render_steps"] = render_steps if carry == "fork" else 0
    cfg = base.with_(**changes)
    jobs = [Job(p, delay, seed_offset + s) for s in range(seeds) for p in policies]
    outcome = run_jobs(cfg, jobs, cache=ResultCache(cache), workers=workers)
    sim: dict[str, dict[str, Any]] = {}
    for spec in policies:
        rs = [r for r in outcome.results if r.policy == spec]
        sim[spec] = {m: mean_ci95([getattr(r, m, None) for r in rs]).to_dict() for m in METRICS}
        sim[spec]["cameras_used"] = mean_ci95([r.n_selected for r in rs]).to_dict()
    sim["_config"] = cfg.to_dict()
    return sim


# --- outputs ---------------------------------------------------------------------------------
def _rows_csv(results: Sequence[dict[str, Any]], sim: dict[str, Any] | None) -> list[dict]:
    rows = []
    for r in results:
        row: dict[str, Any] = {"policy": r["policy"], "n": r["n"]}
        for metric in (*METRICS, "cameras_used", "aoi_used_ms"):
            row[metric] = r[metric]["mean"]
            row[f"{metric}_ci95"] = r[metric]["ci95"]
            if sim is not None and metric in sim.get(r["policy"], {}):
                row[f"sim_{metric}"] = sim[r["policy"]][metric]["mean"]
        rows.append(row)
    return rows


def plot(results: Sequence[dict[str, Any]], sim: dict[str, Any] | None, path: Path,
         title: str) -> Path:
    """PSNR (full and dynamic), SSIM, LPIPS, reward and cameras used per policy, live with
    95% CIs, the virtual clock's curve beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("psnr_db", "PSNR (dB)"), ("psnr_dynamic_db", "dynamic-region PSNR (dB)"),
              ("ssim", "SSIM"), ("lpips", "LPIPS (lower is better)"), ("reward", "reward"),
              ("cameras_used", "cameras used")]
    x = list(range(len(results)))
    labels = [r["policy"] for r in results]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    for ax, (metric, label) in zip(axes.flat, panels, strict=True):
        means = [r[metric]["mean"] for r in results]
        if all(m is None for m in means):
            ax.text(0.5, 0.5, f"{label}: not measured", ha="center", va="center",
                    transform=ax.transAxes)
            ax.set_axis_off()
            continue
        y = [math.nan if m is None else m for m in means]
        err = [r[metric]["ci95"] or 0.0 for r in results]
        ax.errorbar(x, y, yerr=err, fmt="o-", capsize=4, label="live (95% CI)")
        if sim is not None:
            sy = [sim.get(p, {}).get(metric, {}).get("mean") for p in labels]
            if any(v is not None for v in sy):
                se = [sim.get(p, {}).get(metric, {}).get("ci95") or 0.0 for p in labels]
                ax.errorbar(x, [math.nan if v is None else v for v in sy], yerr=se,
                            fmt="s--", capsize=4, color="grey", label="virtual clock")
        ax.set_xticks(x, labels)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if metric == "psnr_db":
            ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _table(results: Sequence[dict[str, Any]], sim: dict[str, Any] | None) -> Table:
    table = Table(title="live sweep (mean ± 95% CI per render)")
    cols = ["policy", "n", "PSNR (dB)", "dyn. PSNR", "SSIM", "LPIPS", "reward", "cameras",
            "AoI used (ms)"]
    if sim is not None:
        cols += ["sim PSNR", "live − sim (dB)"]
    for c in cols:
        table.add_column(c, justify="right")

    def cell(stat: dict[str, Any], digits: int) -> str:
        return fmt(stat.get("mean"), stat.get("ci95"), digits)

    for r in results:
        cells = [escape(r["policy"]), str(r["n"]), cell(r["psnr_db"], 2),
                 cell(r["psnr_dynamic_db"], 2), cell(r["ssim"], 3), cell(r["lpips"], 3),
                 cell(r["reward"], 3), cell(r["cameras_used"], 1), cell(r["aoi_used_ms"], 0)]
        if sim is not None:
            s = sim.get(r["policy"], {}).get("psnr_db", {}).get("mean")
            live = r["psnr_db"]["mean"]
            cells += [fmt(s, None, 2),
                      "—" if s is None or live is None else f"{live - s:+.2f}"]
        table.add_row(*cells)
    return table


def plot_views(measurements: Sequence[Measurement], dataset: Path, path: Path,
               title: str) -> Path | None:
    """Each policy's last render (of its last window) beside the ground truth of the same
    time (the held-out camera's frame at the scene time the metrics service paired it with)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from PIL import Image

    from aoi3d.scene import open_dataset

    last = {m.policy: m for m in measurements}  # the last window of each policy
    pairs = []
    for m in last.values():
        entry = next((q for q in m.qualities if q["decision_id"] == m.render_decision), None)
        if not m.render_png or entry is None:
            continue
        pairs.append((m, entry, np.asarray(Image.open(io.BytesIO(m.render_png)).convert("RGB"))))
    if not pairs:
        return None
    try:
        ds = open_dataset(dataset)
    except (OSError, ValueError) as err:  # the truth is only for this figure: say so, go on
        console.print("no views figure: cannot read the dataset for the truth "
                      f"({escape(str(err))})")
        return None
    fig, axes = plt.subplots(2, len(pairs), figsize=(3.2 * len(pairs), 5.2), squeeze=False,
                             constrained_layout=True)
    for col, (m, entry, image) in enumerate(pairs):
        truth = ds.frame(ds.heldout_id, ds.frame_index(entry["scene_time_ms"]))
        axes[0, col].imshow(image, interpolation="nearest")
        axes[0, col].set_title(f"{m.policy} (repeat {m.repeat + 1})\n"
                               f"{entry['psnr_db']:.1f} dB, {entry['n_views']} views", fontsize=9)
        axes[1, col].imshow(truth, interpolation="nearest")
        axes[1, col].set_title(f"truth, t = {entry['time_ms']:.0f} ms", fontsize=9)
        for ax in axes[:, col]:
            ax.set_axis_off()
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# --- starting a pipeline ---------------------------------------------------------------------
def _start_pipeline(port_offset: int, zenoh_port: int, time_scale: float, run_id: str,
                    timeout_s: float, extra: Sequence[str]) -> subprocess.Popen:
    cmd = [sys.executable, "-c", "from aoi3d_cli import main; main()", "up", "--quiet",
           "--port-offset", str(port_offset), "--zenoh-port", str(zenoh_port),
           "--time-scale", str(time_scale), "--run-id", run_id, *extra]
    console.print(f"starting the pipeline: aoi3d {escape(' '.join(cmd[3:]))}")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    return proc


def _stop_pipeline(proc: subprocess.Popen) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _policy_json(spec: str) -> dict[str, Any]:
    from aoi3d.policy import parse_policy

    try:
        return parse_policy(spec).to_json()
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="'--policies'") from None


# --- the command -----------------------------------------------------------------------------
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
        help="POST /reset on the trainer after each policy change.")] = True,
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
) -> None:
    """Measure each policy on the running pipeline; write CSV, JSON and a PNG with the
    virtual clock's curve beside the live one.

    Reports, per metric, whether the best policy is an interior maximum beyond its 95%
    confidence interval: neither end of --policies, and the Welch (unpaired: the windows are
    different renders, not seeds) 95% CI of best − each end above zero."""
    specs = [s.strip() for s in policies.split(",") if s.strip()]
    if len(specs) < 2:
        raise typer.BadParameter("give at least two policies", param_hint="'--policies'")
    bodies = {s: _policy_json(s) for s in specs}
    if delay is not None:
        from aoi3d.channel import DelaySpecError, parse_channel

        try:
            delay = parse_channel(delay).spec
        except DelaySpecError as err:
            raise typer.BadParameter(str(err), param_hint="'--delay'") from None
    from aoi3d.policy import parse_policy

    canon = {s: parse_policy(s).spec for s in specs}
    proc = None
    if site is not None:
        from aoi3d.ports import check_site

        try:
            check_site(site)
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="'--site'") from None
    pipe = Pipeline(url_base, port_offset, timeout_s, site)
    previous_delay: str | None = None
    started = time.monotonic()
    try:
        if up:
            run_id = f"live-sweep-{os.getpid()}"
            proc = _start_pipeline(port_offset, zenoh_port, time_scale, run_id, timeout_s,
                                   ["--dataset", str(dataset), "--workers", str(workers)])
            _wait("every service to be ready", pipe.ready, 10 * timeout_s, every_s=1.0)
        try:
            status0 = pipe.call("GET", "trainer", "/status")
            channel = pipe.call("GET", "network", "/channel")
            if delay is not None and delay != channel["delay"]:
                previous_delay = channel["delay"]
                channel = pipe.call("PUT", "network", "/channel", json={"delay": delay})
                console.print(f"channel: {escape(delay)} (was {escape(previous_delay)})")
        except LiveError as err:
            console.print(f"[red]error:[/] {escape(str(err))}")
            raise typer.Exit(1) from None
        measurements: list[Measurement] = []
        total = repeats * len(specs)
        for rep in range(repeats):
            for i, spec in enumerate(specs):
                console.print(f"\\[{rep * len(specs) + i + 1}/{total}] {escape(canon[spec])}: "
                              f"settle {settle_s:g} s, measure {measure_s:g} s")
                try:
                    m = measure_policy(pipe, bodies[spec], canon[spec], settle_s=settle_s,
                                       measure_s=measure_s, reset=reset_each, repeat=rep)
                except LiveError as err:
                    console.print(f"[red]error:[/] {escape(str(err))}")
                    raise typer.Exit(1) from None
                measurements.append(m)
                console.print(f"    {len(m.qualities)} renders scored, decisions "
                              f"{m.first_decision}..{m.last_decision}")
        status1 = pipe.call("GET", "trainer", "/status")
        channel_end = pipe.call("GET", "network", "/channel")
        channel["changes"] = channel_end.get("changes", [])
    finally:
        if previous_delay is not None and proc is None:
            try:
                pipe.call("PUT", "network", "/channel", json={"delay": previous_delay})
            except LiveError as err:
                console.print(f"[yellow]could not put the channel back:[/] {escape(str(err))}")
        pipe.close()
        if proc is not None:
            _stop_pipeline(proc)
    live_wall_s = time.monotonic() - started
    order = [canon[s] for s in specs]
    results = summarise(measurements, order)
    carry = status1.get("carry", "warm")
    render_steps = int(status1.get("render_steps") or 0)
    steps_per_s = float(status1.get("steps_per_s") or 0.0)
    sim_doc = None
    if sim:
        console.print(f"virtual clock: {sim_seeds} seed(s) per policy, carry {carry}, "
                      f"{render_steps} steps per rendered decision, delay {channel['delay']}")
        sim_doc = simulate(order, dataset=dataset, delay=channel["delay"], carry=carry,
                           steps_per_decision=_steps_per_decision(status0, status1,
                                                                  measurements),
                           render_steps=render_steps, seeds=sim_seeds,
                           seed_offset=sim_seed_offset, cache=cache, workers=None)
        for r in results:
            s = sim_doc[r["policy"]]["psnr_db"]["mean"]
            live = r["psnr_db"]["mean"]
            r["sim_psnr_db"] = sim_doc[r["policy"]]["psnr_db"]
            r["live_minus_sim_db"] = None if s is None or live is None else live - s
    from aoi3d.experiment.optimum import unpaired_interior_maximum

    shape = {m: unpaired_interior_maximum(results, m) for m in METRICS}
    doc = {
        "results": results,
        "unpaired_interior_maximum": shape,
        "settings": {"policies": order, "settle_s": settle_s, "measure_s": measure_s,
                     "repeats": repeats, "reset_each": reset_each, "port_offset": port_offset,
                     "site": site,
                     "carry": carry, "render_steps": render_steps,
                     "trainer_steps_per_s": steps_per_s, "channel": channel,
                     "backend": status1.get("backend")},
        "sim": sim_doc,
        "wall_s": {"live": live_wall_s, "total": time.monotonic() - started},
        "measurements": [_measurement_doc(m) for m in measurements],
    }
    from aoi3d.experiment.report import code_version, machine, write_csv, write_json

    doc["meta"] = {"code_version": code_version(), "machine": machine(),
                   "finished_unix_s": time.time()}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "results.json", doc)
    write_csv(out / "points.csv", _rows_csv(results, sim_doc))
    write_csv(out / "renders.csv", [
        {"policy": m.policy, "repeat": m.repeat, **{k: v for k, v in q.items()
                                                    if not isinstance(v, list)}}
        for m in measurements for q in m.qualities])
    plot(results, sim_doc, out / "live_sweep.png",
         f"Live sweep — {channel['delay']}, carry {carry}, {render_steps} steps per rendered "
         f"decision, {steps_per_s:.0f} trainer steps/s, {measure_s:g} s × {repeats} per policy")
    plot_views(measurements, dataset, out / "live_views.png",
               "Live renders (top) and the truth of the same time (bottom), the last render "
               "of each policy")
    if json_:
        print(json.dumps({k: doc[k] for k in ("results", "unpaired_interior_maximum",
                                               "settings", "wall_s")}, default=str))
    else:
        stdout = make_console(width=160)
        stdout.print(_table(results, sim_doc))
        for metric, info in shape.items():
            if info is not None:
                verdict = ("an interior maximum beyond its 95% CI (Welch, unpaired)"
                           if info["beyond_ci"] else
                           "interior, but within the CIs of an end" if info["interior"] else
                           "not interior")
                stdout.print(f"{metric}: best {escape(info['best'])} "
                             f"({info['best_mean']:.3f}): {verdict}")
        stdout.print(f"results in {escape(str(out))}")


def _measurement_doc(m: Measurement) -> dict[str, Any]:
    """A window for results.json: its renders' Quality, and of the decisions sampled in it
    only what the summary uses (cameras used, mean AoI of the used frames)."""
    doc = {k: v for k, v in vars(m).items() if k not in ("render_png", "decisions")}
    doc["decisions_sampled"] = [
        {"decision_id": d["decision_id"], "cameras_used": len(d["selected"]),
         "aoi_used_ms": (sum(r["aoi_ms"] for r in d["selected"]) / len(d["selected"])
                         if d["selected"] else None)}
        for d in m.decisions]
    return doc


def _steps_per_decision(s0: dict[str, Any], s1: dict[str, Any],
                        measurements: Sequence[Measurement]) -> int:
    """Background training steps per decision over the sweep (warm/fork carry)."""
    decisions = sum(m.last_decision - m.first_decision + 1 for m in measurements)
    renders = sum(len(m.qualities) for m in measurements)
    steps = s1.get("steps_total", 0) - s0.get("steps_total", 0)
    steps -= renders * int(s1.get("render_steps") or 0)
    return max(1, round(steps / decisions)) if decisions > 0 and steps > 0 else 1
