"""Where a sweep's episodes run: :func:`work` runs one planned episode in any process (plain
data in, plain data out); :func:`run_pool` spreads them over a local process pool (``spawn``),
:func:`run_ray` over a Ray cluster. Each episode process keeps its datasets and LPIPS models
(:data:`DATASETS`)."""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any

from aoi3d.experiment.episode import EpisodePlan, EpisodeResult, run_plan, set_torch_threads
from aoi3d.scene import SceneDataset, open_dataset

__all__ = ["DATASETS", "run_pool", "run_ray", "work"]

DATASETS: dict[str, SceneDataset] = {}
_LPIPS: dict[str, Any] = {}


def _dataset(path: str) -> SceneDataset:
    ds = DATASETS.get(path)
    if ds is None:
        ds = DATASETS[path] = open_dataset(path)
    return ds


def _lpips_fn(device: str) -> Any:
    if device not in _LPIPS:
        from aoi3d.lpips import load_lpips_fn

        _LPIPS[device] = load_lpips_fn(device=device)
    return _LPIPS[device]


def _init_process(threads: int) -> None:
    set_torch_threads(threads)


def work(plan_doc: dict[str, Any], key: str, lpips: bool,
          threads: int | None = None) -> tuple[dict[str, Any], bytes]:
    """Run one planned episode (any process: plain data in, plain data out)."""
    if threads is not None:
        set_torch_threads(threads)
    plan = EpisodePlan.from_dict(plan_doc)
    ds = _dataset(plan.config.dataset)
    lpips_fn = _lpips_fn(plan.config.device) if lpips else None
    if lpips and lpips_fn is None:
        raise RuntimeError("LPIPS weights vanished while the sweep ran")
    result, png = run_plan(plan, ds, key=key, lpips_fn=lpips_fn)
    return result.to_dict(), png


def run_pool(items: list[tuple[dict[str, Any], str]], lpips: bool, processes: int, threads: int,
              done: Callable[[EpisodeResult, bytes], None]) -> None:
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=processes, mp_context=ctx, initializer=_init_process,
                               initargs=(threads,))
    try:
        pending: set[Future[tuple[dict[str, Any], bytes]]] = {
            pool.submit(work, doc, key, lpips) for doc, key in items
        }
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                result, png = fut.result()
                done(EpisodeResult.from_dict(result), png)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def run_ray(items: list[tuple[dict[str, Any], str]], lpips: bool, threads: int, address: str,
             done: Callable[[EpisodeResult, bytes], None]) -> None:
    try:
        import ray
    except ImportError:
        raise RuntimeError("--ray-address needs Ray: pip install '.[cluster]'") from None
    if not ray.is_initialized():
        ray.init(address=None if address == "local" else address,
                 log_to_driver=False, include_dashboard=False)
    remote = ray.remote(num_cpus=threads)(work)
    refs = [remote.remote(doc, key, lpips, threads) for doc, key in items]
    try:
        while refs:
            ready, refs = ray.wait(refs, num_returns=1)
            for ref in ready:
                result, png = ray.get(ref)
                done(EpisodeResult.from_dict(result), png)
    finally:
        for ref in refs:
            ray.cancel(ref)
