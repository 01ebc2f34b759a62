"""Benchmark: the radiance-field backends at fixed wall-clock training budgets.

The synthetic turbine at one instant (frame 0), in two cases: all training cameras (18 by
default), and 6 of them spread evenly across the arc (ids 1, 4, 8, 11, 15, 18 of 18). Every
backend registered in ``aoi3d.field.BACKENDS`` trains from scratch on each case; the quality
of the held-out novel view (camera 0) is scored at the budgets (default 5, 15, 30, 60 s of
*training* time: rendering and scoring are excluded from the clock) as PSNR / SSIM / LPIPS.
The reference, the plain positional-encoding NeRF MLP (backend ``nerf`` when registered),
trains on in the same run up to ``--reference-s`` (180 s): a backend's "time to reference"
is the training time at which its novel view first reaches the MLP's 180-s PSNR (PSNR is
also probed between the budgets, see ``PROBES_S``), and its speed-up is 180 s divided by it.

Also per run: training rays/s (steps × batch_rays / training time), the render time of the
novel view (median of a few renders after training), peak memory (the rise of the process's
resident set from just before the model is built, VmHWM reset through
``/proc/self/clear_refs``; on CUDA also ``torch.cuda.max_memory_allocated``), CPU time next to
wall time, and the load average (other processes skew wall-clock budgets). The machine's fp32
matmul throughput (``torch.mm`` on the same threads) is measured at the start and at the end,
so figures can be read as a fraction of what the hardware does.

Each run happens in a fresh process (``--no-isolate`` runs them in this one): peak memory
and the allocator start clean, and one backend's threads or caches cannot slow the next.

    python -m bench.fields                        # everything (≈ 15 min on 2 cores)
    python -m bench.fields --quick --backends grid  # smoke run (< 1 min)

Writes ``results/fields.json`` (``fields-quick.json`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from bench import common

ROOT = common.ROOT
RESULTS = common.RESULTS
REFERENCE = "nerf"
"""The reference backend: the plain positional-encoding NeRF MLP."""
BUDGETS_S = (5.0, 15.0, 30.0, 60.0)
REFERENCE_S = 180.0
QUICK_BUDGETS_S = (1.0, 2.0, 4.0)
QUICK_REFERENCE_S = 8.0
PROBES_S = (1, 2, 3, 4, 5, 6, 8, 10, 12, 15, 20, 25, 30, 40, 50, 60, 75, 90, 105, 120, 150, 180)
"""Training times (s) at which the novel view's PSNR is also measured (time to reference)."""
SPREAD_CAMERAS = 6
RENDER_REPEATS = 5
MATMUL_SIZE = 2048
Report = Callable[[dict[str, Any]], None]


# ============================================================================ one run
@dataclass(frozen=True)
class RunSpec:
    """One backend trained on one case."""

    dataset: str
    backend: str
    cameras: tuple[int, ...]
    frame: int
    budgets_s: tuple[float, ...]
    probes_s: tuple[float, ...]
    threads: int
    device: str
    seed: int = 0
    render_repeats: int = RENDER_REPEATS
    lpips: bool = True


def _proc_status_mb(key: str) -> float | None:
    """``VmRSS`` / ``VmHWM`` of this process in MiB (Linux), else None."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


class PeakMemory:
    """Rise of the resident set (and of CUDA allocations) since :meth:`start`."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.hwm_reset = False
        self.base_mb: float | None = None

    def start(self) -> None:
        try:  # reset VmHWM to the current RSS (Linux ≥ 4.0)
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
            self.hwm_reset = True
        except OSError:
            self.hwm_reset = False
        self.base_mb = _proc_status_mb("VmRSS")
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._cuda_base = torch.cuda.memory_allocated(self.device)

    def result(self) -> dict[str, Any]:
        hwm = _proc_status_mb("VmHWM")
        out: dict[str, Any] = {
            "rss_delta_mb": None if hwm is None or self.base_mb is None
            else round(hwm - self.base_mb, 1),
            "rss_peak_mb": None if hwm is None else round(hwm, 1),
            "hwm_reset": self.hwm_reset,
            "cuda_peak_mb": None,
        }
        if self.device.type == "cuda":
            peak = torch.cuda.max_memory_allocated(self.device) - self._cuda_base
            out["cuda_peak_mb"] = round(peak / 2**20, 1)
        return out


@functools.cache
def lpips_scorer(enabled: bool) -> tuple[Callable[[np.ndarray, np.ndarray], float] | None, str]:
    """The LPIPS function (AlexNet) and a note saying why it is missing when it is."""
    if not enabled:
        return None, "LPIPS disabled (--no-lpips)"
    from aoi3d.lpips import load_lpips_fn

    fn = load_lpips_fn()
    if fn is None:
        return None, "LPIPS weights not cached: run `python -m aoi3d.lpips fetch`"
    return fn, "LPIPS AlexNet v0.1"


def probe_times(budgets_s: Sequence[float]) -> tuple[float, ...]:
    """``PROBES_S`` up to the last budget, plus the budgets, sorted."""
    last = max(budgets_s)
    return tuple(sorted({float(p) for p in PROBES_S if p <= last} | {float(b) for b in budgets_s}))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_one(spec: RunSpec, report: Report | None = None) -> dict[str, Any]:
    """Train ``spec.backend`` on the case, scoring the novel view at every probe (PSNR) and
    budget (PSNR, SSIM, LPIPS). ``report`` gets a dict after each probe."""
    from aoi3d.field import FieldTrainer, TrainView, field_config
    from aoi3d.field.process import configure_process
    from aoi3d.quality import psnr, ssim
    from aoi3d.scene import load_dataset

    configure_process(spec.threads)  # threads and allocator, as the training programs do
    device = torch.device(spec.device)
    ds = load_dataset(spec.dataset)
    views = [TrainView(ds.cameras[c], ds.frame(c, spec.frame)) for c in spec.cameras]
    camera = ds.cameras[ds.heldout_id]
    truth = ds.frame(ds.heldout_id, spec.frame)
    lpips_fn, lpips_note = lpips_scorer(spec.lpips)
    cfg = field_config(spec.backend, num_threads=spec.threads)
    load_start = os.getloadavg()[0]

    memory = PeakMemory(device)
    memory.start()
    trainer = FieldTrainer(cfg, ds.aabb, device=device, seed=spec.seed)
    trainer.set_views(views)

    budgets = sorted(set(spec.budgets_s))
    probes = sorted(set(spec.probes_s) | set(budgets))
    train_s = cpu_s = 0.0
    checkpoints: list[dict[str, Any]] = []
    probe_log: list[dict[str, Any]] = []
    last_loss = math.nan
    i = 0
    while i < len(probes):
        t0, c0 = time.perf_counter(), time.process_time()
        last_loss = trainer.step(1)
        _sync(device)
        train_s += time.perf_counter() - t0
        cpu_s += time.process_time() - c0
        if train_s < probes[i]:
            continue
        while i < len(probes) and train_s >= probes[i]:  # a slow step may pass several
            i += 1
        r0 = time.perf_counter()
        image = trainer.render(camera)
        render_s = time.perf_counter() - r0
        entry = {"train_s": round(train_s, 3), "cpu_s": round(cpu_s, 3),
                 "steps": trainer.steps, "psnr_db": round(psnr(image, truth), 3),
                 "render_s": round(render_s, 4), "loss": last_loss}
        probe_log.append(entry)
        for b in [b for b in budgets if b <= train_s and b not in
                  {c["budget_s"] for c in checkpoints}]:
            lpips = None
            if lpips_fn is not None:
                try:
                    lpips = round(float(lpips_fn(image, truth.astype(np.float32) / 255.0)), 4)
                except ValueError as err:  # e.g. an image too small for AlexNet
                    lpips_note = f"LPIPS unavailable: {err}"
            checkpoints.append({"budget_s": b, **entry, "ssim": round(ssim(image, truth), 4),
                                "lpips": lpips})
        if report is not None:
            report({"event": "probe", **entry})

    render_times = []
    for _ in range(spec.render_repeats):
        r0 = time.perf_counter()
        trainer.render(camera)
        render_times.append(time.perf_counter() - r0)
    rays = trainer.steps * cfg.batch_rays
    return {
        "backend": spec.backend,
        "config_class": type(cfg).__name__,
        "config": _jsonable(asdict(cfg)) if is_dataclass(cfg) else repr(cfg),
        "cameras": list(spec.cameras),
        "device": str(device),
        "threads": spec.threads,
        "checkpoints": checkpoints,
        "probes": probe_log,
        "steps": trainer.steps,
        "train_s": round(train_s, 3),
        "cpu_s": round(cpu_s, 3),
        "rays_per_s": round(rays / train_s, 1) if train_s > 0 else None,
        "steps_per_s": round(trainer.steps / train_s, 2) if train_s > 0 else None,
        "render_s_median": round(statistics.median(render_times), 4) if render_times else None,
        "render_s_all": [round(t, 4) for t in render_times],
        "memory": memory.result(),
        "lpips_note": lpips_note,
        "loadavg_start": round(load_start, 2),
        "loadavg_end": round(os.getloadavg()[0], 2),
        "error": None,
    }


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, float | int | str | bool) or value is None:
        return value
    return repr(value)


def run_isolated(spec: RunSpec, report: Report | None = None) -> dict[str, Any]:
    """:func:`run_one` in a fresh Python process (JSON lines over its stdout)."""
    cmd = [sys.executable, "-m", "bench.fields", "--run-spec", json.dumps(asdict(spec))]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, bufsize=1)
    result: dict[str, Any] | None = None
    other: list[str] = []
    assert proc.stdout is not None
    for line in proc.stdout:
        msg = None
        if line.startswith("{"):
            try:
                msg = json.loads(line)
            except json.JSONDecodeError:
                msg = None
        if msg is None:
            other.append(line.rstrip())
        elif msg.get("event") == "result":
            result = msg["result"]
        elif report is not None:
            report(msg)
    rc = proc.wait()
    if result is None:
        tail = "\n".join(other[-15:])
        raise RuntimeError(f"run process exited with {rc} and no result:\n{tail}")
    return result


def _child(spec_json: str) -> None:
    spec_dict = json.loads(spec_json)
    for name in ("cameras", "budgets_s", "probes_s"):
        spec_dict[name] = tuple(spec_dict[name])
    spec = RunSpec(**spec_dict)

    def emit(msg: dict[str, Any]) -> None:
        print(json.dumps(msg), flush=True)

    try:
        result = run_one(spec, emit)
    except Exception as err:  # reported to the parent as a failed run
        result = failed(spec, err)
    emit({"event": "result", "result": result})


def failed(spec: RunSpec, err: BaseException) -> dict[str, Any]:
    return {"backend": spec.backend, "cameras": list(spec.cameras), "checkpoints": [],
            "probes": [], "error": f"{type(err).__name__}: {err}"}


# ============================================================================ the machine
def matmul_gflops(size: int, threads: int, device: torch.device,
                  min_time_s: float = 0.2) -> float:
    """fp32 ``torch.mm`` of two size² matrices on ``threads`` CPU threads (or the GPU, TF32
    off): GFLOP/s of the median repetition (2·size³ flops each)."""
    torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(size, size, generator=gen).to(device)
    b = torch.randn(size, size, generator=gen).to(device)
    out = torch.empty_like(a)
    tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        for _ in range(2):
            torch.mm(a, b, out=out)
        _sync(device)
        times: list[float] = []
        started = time.perf_counter()
        while len(times) < 3 or time.perf_counter() - started < min_time_s:
            t0 = time.perf_counter()
            torch.mm(a, b, out=out)
            _sync(device)
            times.append(time.perf_counter() - t0)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = tf32
    return round(2.0 * size**3 / statistics.median(times) / 1e9, 2)


def machine_info(device: torch.device, threads: int, size: int) -> dict[str, Any]:
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f
                          if ln.startswith("model name")), model)
    except OSError:
        pass
    info: dict[str, Any] = {
        "python": platform.python_version(), "torch": torch.__version__,
        "platform": platform.platform(), "cpu": model, "cpu_count": os.cpu_count(),
        "threads": threads, "device": str(device),
        "cuda_device": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "matmul_size": size,
        "matmul_cpu_gflops_start": matmul_gflops(size, threads, torch.device("cpu")),
        "loadavg_start": [round(x, 2) for x in os.getloadavg()],
    }
    if device.type == "cuda":
        info["matmul_cuda_gflops"] = matmul_gflops(max(size, 4096), threads, device)
    return info


def code_version() -> str:
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty", "--tags"], cwd=ROOT,
                             capture_output=True, text=True, timeout=10, check=True)
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# ============================================================================ cases, results
def spread(ids: Sequence[int], k: int) -> list[int]:
    """``k`` of ``ids`` evenly spread (first and last included); all of them if k ≥ len."""
    if k < 1:
        raise ValueError(f"a case needs at least 1 camera, got {k}")
    if k >= len(ids):
        return list(ids)
    return [ids[i] for i in np.round(np.linspace(0, len(ids) - 1, k)).astype(int)]


def case_cameras(name: str, train_ids: Sequence[int]) -> list[int]:
    """Cameras of case ``name``: ``all``, or a number k (k cameras spread across the arc)."""
    if name == "all":
        return list(train_ids)
    try:
        k = int(name)
    except ValueError:
        raise ValueError(f"unknown case {name!r}: use 'all' or a number of cameras") from None
    return spread(train_ids, k)


def time_to_psnr(run: dict[str, Any], target_db: float) -> float | None:
    """Training time of the first probe whose PSNR reaches ``target_db`` (None: never)."""
    for p in run.get("probes", []):
        if p["psnr_db"] >= target_db:
            return p["train_s"]
    return None


def compare_to_reference(runs: dict[str, dict[str, Any]], reference_s: float) -> dict[str, Any]:
    """The reference's PSNR at ``reference_s`` and, per backend, the time to reach it and the
    speed-up ``reference_s / time``."""
    ref = runs.get(REFERENCE)
    if ref is None or ref.get("error"):
        why = "not in this run" if ref is None else f"failed: {ref['error']}"
        return {"reference": REFERENCE, "note": f"reference {REFERENCE!r} {why}",
                "target_psnr_db": None, "backends": {}}
    at = [c for c in ref["checkpoints"] if c["budget_s"] == reference_s]
    if not at:
        return {"reference": REFERENCE, "note": f"reference has no {reference_s:g}-s checkpoint",
                "target_psnr_db": None, "backends": {}}
    target = at[0]["psnr_db"]
    out: dict[str, Any] = {}
    for name, run in runs.items():
        t = time_to_psnr(run, target) if not run.get("error") else None
        longest = max((c["budget_s"] for c in run.get("checkpoints", [])), default=None)
        out[name] = {"time_s": t, "speedup": round(reference_s / t, 2) if t else None,
                     "trained_s": longest}
    return {"reference": REFERENCE, "reference_s": reference_s, "target_psnr_db": target,
            "note": "time = first PSNR probe at or above the target (probe resolution)",
            "backends": out}


def print_case(console: Console, name: str, case: dict[str, Any], budgets: Sequence[float],
               reference_s: float | None) -> None:
    """One table per case: PSNR at each budget, SSIM and LPIPS at the last common budget,
    speed, render time, memory, time to the reference's PSNR and the speed-up."""
    last = max(budgets)
    cols = list(budgets) + ([reference_s] if reference_s and reference_s not in budgets else [])
    table = Table(title=f"case {name}: {len(case['cameras'])} training cameras "
                        f"{case['cameras']}, novel view = camera {case['heldout']}, frame "
                        f"{case['frame']}; PSNR (dB) after t s of training",
                  title_justify="left")
    table.add_column("method")
    for b in cols:
        table.add_column(f"{b:g} s", justify="right")
    for col in (f"SSIM/LPIPS {last:g} s", "rays/s", "render", "peak MB", "t→ref", "speed-up"):
        table.add_column(col, justify="right")
    cmp = case["reference"]["backends"]
    for backend, run in case["runs"].items():
        if run.get("error"):
            table.add_row(backend, f"[red]{run['error'][:80]}[/]", *[""] * (len(cols) + 5))
            continue
        by_budget = {c["budget_s"]: c for c in run["checkpoints"]}
        at_last = by_budget.get(last)
        quality = "" if at_last is None else (
            f"{at_last['ssim']:.3f}/" + ("—" if at_last["lpips"] is None
                                         else f"{at_last['lpips']:.3f}"))
        mem = run["memory"]
        peak = mem["cuda_peak_mb"] if mem.get("cuda_peak_mb") is not None else mem["rss_delta_mb"]
        c = cmp.get(backend, {})
        t = c.get("time_s")
        if not cmp:
            t_text, s_text = "n/a", "n/a"
        elif t is None:
            t_text, s_text = f"> {c.get('trained_s') or 0:g} s", "—"
        else:
            t_text, s_text = f"{t:.1f} s", f"{c['speedup']:.1f}×"
        table.add_row(
            backend,
            *["" if b not in by_budget else f"{by_budget[b]['psnr_db']:.2f}" for b in cols],
            quality,
            f"{run['rays_per_s']:,.0f}" if run.get("rays_per_s") else "—",
            f"{run['render_s_median'] * 1000:.0f} ms" if run.get("render_s_median") else "—",
            "—" if peak is None else f"{peak:.0f}", t_text, s_text)
    console.print(table)
    ref = case["reference"]
    if ref["target_psnr_db"] is None:
        console.print(f"  time to reference: {ref['note']}")
    else:
        console.print(f"  t→ref: training time to reach {REFERENCE} at {ref['reference_s']:g} s "
                      f"= {ref['target_psnr_db']:.2f} dB ({ref['note']}); speed-up = "
                      f"{ref['reference_s']:g} s / t→ref")


# ============================================================================ main
def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated seconds, got {text!r}") \
            from None
    if not values or min(values) <= 0:
        raise argparse.ArgumentTypeError(f"budgets must be > 0 s, got {text!r}")
    return values


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backends", default="all",
                    help="comma-separated backend names, or 'all' (every registered one)")
    ap.add_argument("--budgets", type=_floats, default=None,
                    help=f"training seconds to score at (default {BUDGETS_S})")
    ap.add_argument("--reference-s", type=float, default=None,
                    help=f"training seconds of the reference {REFERENCE!r} (default "
                         f"{REFERENCE_S:g})")
    ap.add_argument("--cases", default=f"all,{SPREAD_CAMERAS}",
                    help="comma-separated: 'all' (every training camera) or a number k "
                         "(k cameras spread across the arc)")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    ap.add_argument("--quick", action="store_true",
                    help=f"smoke run: budgets {QUICK_BUDGETS_S}, reference "
                         f"{QUICK_REFERENCE_S:g} s, smaller matmul, fewer renders")
    ap.add_argument("--dataset", default=str(ROOT / "data" / "turbine"),
                    help="aoi3d dataset (generated with the default scene if missing)")
    ap.add_argument("--frame", type=int, default=0, help="frame index (one instant)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--matmul-size", type=int, default=None)
    ap.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    ap.add_argument("--no-isolate", action="store_true",
                    help="run every backend in this process (no fresh process per run)")
    ap.add_argument("--out", default=None, help="JSON file (default results/fields.json, "
                                                "fields-quick.json with --quick)")
    ap.add_argument("--run-spec", help=argparse.SUPPRESS)
    common.add_json_option(ap)
    args = ap.parse_args(argv)
    if args.threads < 1:
        ap.error("--threads must be >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Parses the options (``--run-spec``: one run, in the fresh process of
    :func:`run_isolated`) and runs; returns the result document (``--json``: prints it)."""
    args = parse_args(argv)
    if args.run_spec:
        _child(args.run_spec)
        return {}
    if not args.json:
        return run(args)
    with common.progress_to_stderr():
        result = run(args)
    common.print_json(result)
    return result


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Every case and backend (``parse_args``'s options); writes ``args.out`` (or the default
    under results/) and returns the result document."""
    from aoi3d.field import BACKENDS, UnknownBackendError, check_backend
    from aoi3d.scene import SceneConfig, ensure_dataset, load_dataset

    console = Console(width=max(Console().width, 120))  # the table, also in logs
    budgets = args.budgets or (QUICK_BUDGETS_S if args.quick else BUDGETS_S)
    reference_s = args.reference_s or (QUICK_REFERENCE_S if args.quick else REFERENCE_S)
    if args.backends == "all":
        backends = list(BACKENDS)
    else:
        backends = [b.strip() for b in args.backends.split(",") if b.strip()]
        try:
            for b in backends:
                check_backend(b)
        except UnknownBackendError as err:
            raise SystemExit(str(err)) from None
    if args.device == "auto":
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    elif args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: CUDA is not available here")
    else:
        device = torch.device(args.device)

    path = Path(args.dataset)
    if path.exists():
        ds = load_dataset(path)
    else:
        console.print(f"generating the default scene at {path} …")
        ds = ensure_dataset(path, SceneConfig())
    if not 0 <= args.frame < ds.n_frames:
        raise SystemExit(f"--frame must be in 0..{ds.n_frames - 1}, got {args.frame}")
    cases = {name: case_cameras(name, ds.train_ids)
             for name in (c.strip() for c in args.cases.split(",")) if name}

    size = args.matmul_size or (1024 if args.quick else MATMUL_SIZE)
    machine = machine_info(device, args.threads, size)
    console.print(f"{machine['cpu']} ({machine['cpu_count']} CPUs), {args.threads} threads, "
                  f"device {device}; fp32 matmul {size}²: "
                  f"{machine['matmul_cpu_gflops_start']:.1f} GFLOP/s; load "
                  f"{machine['loadavg_start']}")
    busy = machine["loadavg_start"][0] > 0.5 * (os.cpu_count() or 1)
    if busy and device.type == "cpu":
        console.print("[yellow]warning:[/] the machine is busy (load "
                      f"{machine['loadavg_start'][0]:.1f} on {os.cpu_count()} CPUs): wall-clock "
                      "budgets will understate every backend; compare CPU times (cpu_s) or "
                      "run on a quiet machine")
    runner = run_one if args.no_isolate else run_isolated
    result: dict[str, Any] = {
        "benchmark": "radiance fields: novel-view quality at fixed training budgets",
        "code_version": code_version(),
        "config": {
            "dataset": str(path), "scene": ds.config, "width": ds.width, "height": ds.height,
            "frame": args.frame, "heldout": ds.heldout_id, "budgets_s": list(budgets),
            "reference": REFERENCE, "reference_s": reference_s, "threads": args.threads,
            "device": str(device), "quick": args.quick, "seed": args.seed,
            "render_repeats": 3 if args.quick else RENDER_REPEATS, "backends": backends,
            "isolated": not args.no_isolate,
            "budget_note": "training time only: rendering and scoring are not counted",
        },
        "machine": machine,
        "cases": {},
    }
    for case_name, cameras in cases.items():
        runs: dict[str, dict[str, Any]] = {}
        for backend in backends:
            b_budgets = tuple(sorted(set(budgets) | ({reference_s} if backend == REFERENCE
                                                      else set())))
            spec = RunSpec(dataset=str(path), backend=backend, cameras=tuple(cameras),
                           frame=args.frame, budgets_s=b_budgets, probes_s=probe_times(b_budgets),
                           threads=args.threads, device=str(device), seed=args.seed,
                           render_repeats=result["config"]["render_repeats"],
                           lpips=not args.no_lpips)
            with Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                          TextColumn("{task.fields[info]}"), TimeElapsedColumn(),
                          console=console, transient=True) as bar:
                task = bar.add_task(f"{case_name}: {backend}", total=max(b_budgets), info="")

                def report(msg: dict[str, Any], bar=bar, task=task) -> None:
                    if msg.get("event") == "probe":
                        bar.update(task, completed=msg["train_s"],
                                   info=f"{msg['steps']} steps, {msg['psnr_db']:.2f} dB")

                try:
                    runs[backend] = runner(spec, report)
                except Exception as err:  # one broken backend must not stop the others
                    runs[backend] = failed(spec, err)
            run = runs[backend]
            console.print(f"  {case_name}: {backend}: "
                          + (f"[red]{run['error']}[/]" if run.get("error") else
                             ", ".join(f"{c['budget_s']:g} s {c['psnr_db']:.2f} dB"
                                       for c in run["checkpoints"])))
        result["cases"][case_name] = {
            "cameras": cameras, "heldout": ds.heldout_id, "frame": args.frame, "runs": runs,
            "reference": compare_to_reference(runs, reference_s),
        }
    machine["matmul_cpu_gflops_end"] = matmul_gflops(size, args.threads, torch.device("cpu"))
    machine["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    lpips_notes = {r.get("lpips_note") for c in result["cases"].values()
                   for r in c["runs"].values() if r.get("lpips_note")}
    result["lpips_note"] = "; ".join(sorted(lpips_notes)) or None

    for case_name, case in result["cases"].items():
        print_case(console, case_name, case, budgets,
                   reference_s if REFERENCE in backends else None)
    console.print(f"fp32 matmul {size}² on {args.threads} threads: "
                  f"{machine['matmul_cpu_gflops_start']:.1f} → "
                  f"{machine['matmul_cpu_gflops_end']:.1f} GFLOP/s (start → end); load "
                  f"{machine['loadavg_start']} → {machine['loadavg_end']}")
    if result["lpips_note"]:
        console.print(f"LPIPS: {result['lpips_note']}")
    out = Path(args.out) if args.out else RESULTS / ("fields-quick.json" if args.quick
                                                     else "fields.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    console.print(f"written to {out}")
    return result


if __name__ == "__main__":
    main()
