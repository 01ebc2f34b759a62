"""``aoi3d up``: the whole live pipeline on this machine.

Before anything starts: every port of the run (each service's REST port and the Zenoh port,
from :data:`services.kit.ports.SERVICE_PORTS`) must be free — a taken one is one line naming it and
the option that moves it — and the dataset must be readable, every frame file present and
whole. The scene is generated only into the framing's own folder (``data/turbine-rotor``,
``data/turbine``) or with ``--generate``; any other folder must hold a dataset already.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from aoi3d.scene.framings import DEFAULT_FRAMING, FRAMING_DATASETS, FRAMING_SCENES
from aoi3d.sites import site_names
from aoi3d_cli.common import fail, fail_lines
from services.kit.ports import REST_FIRST as _FIRST
from services.kit.ports import REST_LAST as _LAST
from services.kit.ports import SERVICE_PORTS, ZENOH_PORT

if TYPE_CHECKING:
    from rich.console import Console

    from aoi3d.rigfile import Rig
    from services.supervisor import Supervisor, UpConfig

HINTS = {
    "camera": "GET /config",
    "network": "GET /channel",
    "scheduler": "GET /aoi, PUT /policy",
    "dispatcher": "GET /status, /render.png",
    "metrics": "GET /quality?limit=5",
    "console": "open / in a browser",
    "recorder": "GET /recording, POST /recording/start",
    "viewer": "open / in a browser (3D)",
}
"""What to try first on each service (a service without a hint shows its /docs)."""


def up(
    framing: Annotated[str, typer.Option(
        help="Which scene: rotor (the rotor close-up at 6 rpm, the experiments' scene) or site "
             "(the whole turbine at 18 rpm). Sets the default --dataset folder and the scene "
             "generated there.")] = DEFAULT_FRAMING,
    dataset: Annotated[Path | None, typer.Option(
        help=f"Scene dataset folder, any layout `aoi3d scene info` reads. Default: the "
             f"framing's, {FRAMING_DATASETS['rotor']} (rotor) or {FRAMING_DATASETS['site']} "
             "(site), where the scene is generated when missing or stale; any other folder "
             "must hold a dataset (or give --generate).")] = None,
    generate: Annotated[bool, typer.Option(
        help="Generate the framing's scene at --dataset if it is missing or stale, whatever "
             "the folder.")] = False,
    time_scale: Annotated[float | None, typer.Option(
        help="Simulation seconds per wall second; < 1 slows the world so the CPU workers "
             "keeps pace. Default: 0.1, or with --rig the rig file's time_scale (1 for a real "
             "robot; a played dataset's --time-scale).")] = None,
    rig: Annotated[Path | None, typer.Option(
        help="A rig file of real cameras (ROS 2 over Zenoh, docs/real-cameras.md): the ingest "
             "service takes their frames instead of the camera emulators, on the camera's "
             "port; the dataset is not read.")] = None,
    delay: Annotated[str | None, typer.Option(
        help="The network emulator's delay spec (exp:60, const:40, …). With --rig: emulated "
             "delay added on top of the real link, from each frame's receipt; without it the "
             "emulator steps aside and frames are delivered at their receipt.")] = None,
    run_id: Annotated[str, typer.Option(help="Run id: the <run> in every key expression.")]
    = "default",
    sites: Annotated[int, typer.Option(
        min=1, max=16,
        help="Sites (turbines) of the run: site1 … siteS, each with its own cameras (the scene "
             "at its own phase), channel, policy and quality, sharing the worker pool. Each "
             "service's REST paths address site1; /sites/<site>/… any site.")] = 1,
    workers: Annotated[str, typer.Option(
        help="Reconstruction workers in the pool (python -m services.recon, 1 torch thread "
             "each): each renders the newest decision no other worker took; 0 to 64, or auto "
             "(default): every core up to 2, one core left to the services beyond "
             "(docs/performance.md, Streaming reconstruction). More can join from anywhere "
             "that reaches the router (see "
             "GET /workers on the trainer, the pool's dispatcher). Not `aoi3d experiment "
             "--workers` (local processes that run episodes).")] = "auto",
    zenoh_port: Annotated[int, typer.Option(
        min=1, max=65535, help="TCP port of the local Zenoh router.")] = ZENOH_PORT,
    port_offset: Annotated[int, typer.Option(
        help=f"Added to the default REST ports {_FIRST}..{_LAST} (one per service).")] = 0,
    log_dir: Annotated[Path, typer.Option(
        help="Each run logs to a new folder <log-dir>/<run-id>-<UTC start time>/ (one log per "
             "process and up.json); <log-dir>/latest points at the newest.")]
    = Path("runs/logs"),
    ready_timeout_s: Annotated[float, typer.Option(
        min=1, help="Start-up fails unless every service is healthy within this many "
                    "seconds (a service that exits twice before fails it at once).")] = 120.0,
    duration_s: Annotated[float | None, typer.Option(
        help="Stop after this many seconds (default: run until Ctrl-C).")] = None,
    quiet: Annotated[bool, typer.Option(
        help="Do not echo the services' logs to the console.")] = False,
    record: Annotated[Path | None, typer.Option(
        help="Record the run from the start into this MCAP file (docs/recording.md): every "
             "delivered and truth frame as a Foxglove image with its calibration and pose, "
             "decisions, renders, Quality and outcomes. `aoi3d replay FILE` re-runs it. "
             "Without it the recorder idles until POST /recording/start.")] = None,
    record_max_mb: Annotated[float, typer.Option(
        min=0, help="Size cap of one recording segment in MiB (0: none): it rotates into "
                    "<stem>.part2.mcap, part3 … (nothing deleted); a full disk stops it.")] = 0.0,
) -> None:
    """Run the Zenoh router and the pipeline's services locally, supervised, until Ctrl-C (on
    real cameras with --rig). The ports and the dataset (or rig file) are checked first: a
    taken port, a dataset that cannot be read or a service that does not become healthy is
    one line and exit status 1."""
    # the one import of services in aoi3d: `up` composes them (docs/architecture.md)
    from services.supervisor import Supervisor, UpConfig, auto_workers

    if framing not in FRAMING_SCENES:
        raise typer.BadParameter(f"expected one of {', '.join(FRAMING_SCENES)}, got "
                                 f"{framing!r}", param_hint="'--framing'")
    if not 0 < _FIRST + port_offset <= _LAST + port_offset < 65536:
        raise typer.BadParameter(f"the REST ports {_FIRST + port_offset}.."
                                 f"{_LAST + port_offset} are not valid ports",
                                 param_hint="'--port-offset'")
    n_workers = auto_workers() if workers == "auto" else _n_workers(workers)
    folder = dataset if dataset is not None else Path(FRAMING_DATASETS[framing])
    real = _read_rig(rig, sites) if rig is not None else None
    if delay is not None:
        from aoi3d.channel import parse_delay

        try:
            delay = parse_delay(delay).spec
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="'--delay'") from None
    if time_scale is None:
        time_scale = real.time_scale if real is not None else 0.1
    extra_env = {}
    if real is not None:
        extra_env["AOI3D_METRICS_TRUTH_PERIOD_MS"] = repr(real.truth_period_ms)
    cfg = UpConfig(dataset=folder, run_id=run_id, time_scale=time_scale, workers=n_workers,
                   sites=sites, rig=rig, delay=delay, extra_env=extra_env,
                   cameras=len(real.train) if real is not None else 18,
                   zenoh_port=zenoh_port, port_offset=port_offset, log_dir=log_dir,
                   duration_s=duration_s, echo=not quiet, ready_timeout_s=ready_timeout_s)
    if record is not None:
        cfg.extra_env.update(_recorder_env(record, record_max_mb))
    _check_ports(cfg)
    if real is None:
        own = folder.absolute() == Path(FRAMING_DATASETS[framing]).absolute()
        _ensure_scene(folder, framing, generate=generate or own)

    from aoi3d_cli.common import make_console

    console = make_console()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s up %(levelname)s: %(message)s")
    sup = Supervisor(cfg, on_ready=lambda sup: _show_where(console, cfg, real, sup))
    code = sup.run()
    if code and sup.failure:
        fail(f"the pipeline did not start: {sup.failure}", code)
    raise typer.Exit(code)


def _n_workers(workers: str) -> int:
    """--workers as a number of workers (not auto): 0..64."""
    try:
        n_workers = int(workers)
    except ValueError:
        n_workers = -1
    if not 0 <= n_workers <= 64:
        raise typer.BadParameter(f"expected an integer 0..64 or auto, got {workers!r}",
                                 param_hint="'--workers'")
    return n_workers


def _recorder_env(record: Path, record_max_mb: float) -> dict[str, str]:
    """The recorder's settings for --record (its folder made and writable)."""
    if record.is_dir():
        raise typer.BadParameter(f"{record} is a folder; give a file such as "
                                 f"{record / 'run.mcap'}", param_hint="'--record'")
    import os

    try:
        record.resolve().parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        fail(f"cannot make the folder of --record {record}: {err}")
    if not os.access(record.resolve().parent, os.W_OK):
        fail(f"cannot write --record {record}: its folder is not writable")
    return {"AOI3D_RECORDER_PATH": str(record.resolve()),
            "AOI3D_RECORDER_MAX_BYTES": str(int(record_max_mb * 2**20))}


def _check_ports(cfg: UpConfig) -> None:
    """Every port of the run is free, or one line names the first taken and its option."""
    from services.supervisor import taken_ports

    taken = taken_ports(cfg)
    if taken:
        name, port = taken[0]
        option = ("--zenoh-port" if name == "router"
                  else f"--port-offset (REST ports {_FIRST}..{_LAST} + offset)")
        what = "the Zenoh router" if name == "router" else f"the {name} service"
        others = f" (also taken: {', '.join(str(p) for _, p in taken[1:])})" if taken[1:] else ""
        fail(f"port {port} for {what} is in use{others} — is another pipeline running? "
             f"Choose another with {option}.")


def _show_where(console: Console, cfg: UpConfig, real: Rig | None, sup: Supervisor) -> None:
    """Once every service is healthy: where each one is, what to try, where the logs go."""
    from rich.table import Table

    table = Table(title=f"aoi3d pipeline up (run '{cfg.run_id}', time scale {cfg.time_scale})")
    for col in ("service", "REST API (docs at /docs)", "try"):
        table.add_column(col, no_wrap=True)
    for name in SERVICE_PORTS:
        if name == "camera" and real is not None:
            src = real.source
            where = {"rmw_zenoh": f"rmw_zenoh, domain {src.domain_id}",
                     "dds": f"DDS, domain {src.domain_id}, {src.interface}"}.get(
                src.format, f"bridge, namespace '{src.prefix}'")
            table.add_row(f"ingest ({where})", f"http://127.0.0.1:{cfg.port(name)}",
                          "GET /status")
            continue
        table.add_row(name, f"http://127.0.0.1:{cfg.port(name)}", HINTS.get(name, "/docs"))
    table.add_row("router", f"tcp/127.0.0.1:{cfg.zenoh_port}", "Zenoh, multicast off")
    table.add_row(f"recon × {cfg.workers}", "no REST API (pull work over Zenoh)",
                  f"http://127.0.0.1:{cfg.port('dispatcher')}/workers")
    console.print(table)
    console.print(f"[bold]Console: http://127.0.0.1:{cfg.port('console')}/[/bold] "
                  "(the novel view, AoI, quality over time, controls)", soft_wrap=True)
    console.print(f"[bold]3D viewer: http://127.0.0.1:{cfg.port('viewer')}/[/bold] "
                  "(orbit the live reconstruction; cameras coloured by AoI)", soft_wrap=True)
    sched = f"http://127.0.0.1:{cfg.port('scheduler')}/policy"
    if cfg.sites > 1:
        console.print(f"Sites: {', '.join(site_names(cfg.sites))} — "
                      f"e.g. http://127.0.0.1:{cfg.port('scheduler')}/sites/site2/policy",
                      soft_wrap=True)
    console.print(f"Change MAT: curl -X PUT {sched} -H 'content-type: application/json' "
                  """-d '{"kind":"mat","mat_ms":130}'""", soft_wrap=True)
    if real is not None:
        link = (f"the emulated link ({cfg.delay}) adds its delay on top of the real one"
                if cfg.delay else "the link is real: frames are delivered at their receipt "
                                  "(the network emulator steps aside)")
        score = (f"truth camera {real.truth} scores every render" if real.truth else
                 "no truth camera in the rig: renders are made but cannot be scored")
        console.print(f"Real cameras ({cfg.rig}): {len(real.train)} training cameras; {link}; "
                      f"{score}.", soft_wrap=True)
    console.print(f"Logs: {sup.log_dir}/<service>.log ({cfg.log_dir}/latest) · Prometheus "
                  "metrics: <service>/metrics · stop with Ctrl-C", soft_wrap=True)


def _read_rig(path: Path, sites: int):
    """The rig file, validated (one line per bad field ends the command)."""
    from aoi3d.rigfile import RigError, load_rig

    if sites != 1:
        raise typer.BadParameter("a rig is one site", param_hint="'--sites'")
    try:
        return load_rig(path, videos=True)
    except RigError as err:
        fail_lines(err)


def _ensure_scene(dataset: Path, framing: str, *, generate: bool) -> None:
    """Check the dataset at ``dataset`` (any layout; every frame file present and whole); with
    ``generate``, first (re)generate the framing's scene there when it is missing, damaged or
    of another config. A dataset that cannot be used ends the command with one line."""
    import time

    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from aoi3d.scene import DatasetError, detect_layout, ensure_dataset, open_dataset
    from aoi3d_cli.common import make_console

    console = make_console()
    if not generate:
        try:
            detect_layout(dataset)
            ds = open_dataset(dataset, verify=True)
        except DatasetError as err:
            extra = "" if dataset.exists() else f" (or add --generate to make the {framing} scene)"
            fail(f"{err}{extra}")
        console.print(f"scene: {dataset} ({ds.layout} layout, {len(ds.cameras)} cameras × "
                      f"{ds.n_frames} frames, {ds.width}×{ds.height})")
        return
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/"
                  "{task.total}"), TimeRemainingColumn(), console=console,
                  transient=True) as progress:
        task = None

        def report(done: int, total: int) -> None:
            nonlocal task
            if task is None:
                task = progress.add_task(f"generating the {framing} scene into {dataset}",
                                         total=total)
            progress.update(task, completed=done)

        t0 = time.perf_counter()
        try:
            ds = ensure_dataset(dataset, FRAMING_SCENES[framing], progress=report)
        except (DatasetError, FileExistsError) as err:
            fail(err)
    made = f", generated in {time.perf_counter() - t0:.1f} s" if task is not None else ""
    console.print(f"scene: {dataset} ({framing} framing, {len(ds.cameras)} cameras × "
                  f"{ds.n_frames} frames, {ds.width}×{ds.height}{made})")
