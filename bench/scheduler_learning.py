"""Benchmark: online PPO learning in the scheduler, and what it costs the decisions.

Runs the scheduler worker (in-process, MemoryBus, real clock) with a learning ``ppo`` policy
at a high decision rate, and answers every Decision at once with a Quality whose reward is
a toy bandit: +1 per odd camera selected, −1 per even one, divided by N. Every decision is
rewarded (in the live pipeline only rendered ones are), so an update runs every
``batch`` decisions — a stress case for "updates must not delay decisions".

Reports the decisions' lateness (wall time of publishing minus the wall time of the decision
epoch), epochs skipped, the updates' wall time and the mean reward of the first and last
updates (it should rise: the toy bandit's best action is the odd cameras). Writes
``results/scheduler-learning.json``.

Run: ``python -m bench.scheduler_learning [--seconds 20] [--period-ms 30] [--batch 8] [--json]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from prometheus_client import CollectorRegistry

from aoi3d.clock import SimClock
from aoi3d.policy import PPOPolicy
from aoi3d.policy.ppo import PPOConfig
from aoi3d.policy.ppo.learner import PPOLearner
from aoi3d.rl.online import LearnConfig
from aoi3d.scene.camera import Camera, look_at
from bench import common
from services.kit.codec import encode_frame, encode_png
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.scheduler.runtime import SchedulerRuntime

N_CAMERAS = 18
KEYS = Keys("bench")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="Wall seconds to run.")
    ap.add_argument("--period-ms", type=float, default=30.0,
                    help="Decision period (time scale 1: wall ms).")
    ap.add_argument("--batch", type=int, default=8, help="Rewarded decisions per update.")
    ap.add_argument("--threads", type=int, default=1, help="Torch CPU threads.")
    common.add_json_option(ap)
    return ap


def run(seconds: float = 20.0, period_ms: float = 30.0, batch: int = 8,
        threads: int = 1) -> dict[str, Any]:
    """The measurement; writes ``results/scheduler-learning.json`` and returns it."""
    torch.set_num_threads(threads)

    tmp = Path(tempfile.mkdtemp(prefix="aoi3d-bench-"))
    ckpt = tmp / "agent.pt"
    PPOLearner(PPOConfig(n_cameras=N_CAMERAS, seed=0)).save(ckpt)
    policy = PPOPolicy.from_checkpoint(ckpt, learn=True)  # as a PUT with learn: true
    bus = MemoryBus()
    clock = SimClock(epoch_s=time.time(), time_scale=1.0)
    registry = CollectorRegistry()
    worker = SchedulerRuntime(bus, registry, run_id="bench", n_cameras=N_CAMERAS, clock=clock,
                             policy=policy, decision_period_ms=period_ms,
                             learn=LearnConfig(batch_size=batch, checkpoint_every=10))

    lateness_ms: list[float] = []
    sign = np.array([1.0 if cam % 2 else -1.0 for cam in range(1, N_CAMERAS + 1)])

    def on_decision(key: str, payload: bytes) -> None:  # runs on the decision thread
        d = pb.Decision.FromString(payload)
        lateness_ms.append((time.time() - clock.wall_s(d.time_ms)) * 1000.0)
        chosen = np.zeros(N_CAMERAS)
        for ref in d.selected:
            chosen[ref.camera_id - 1] = 1.0
        reward = float(sign @ chosen) / N_CAMERAS
        # the scheduler learns only from its own incarnation's decisions (as the dispatcher sends)
        bus.publish(KEYS.quality, pb.Quality(decision_id=d.decision_id, time_ms=d.time_ms,
                                             decision_incarnation=d.incarnation,
                                             reward=reward).SerializeToString())

    bus.subscribe(KEYS.decision, on_decision)
    camera = Camera(c2w=look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0, fy=20.0, cx=8,
                    cy=6, width=16, height=12)
    image = encode_png(np.zeros((12, 16, 3), np.uint8))
    stop = threading.Event()

    def feed() -> None:  # every camera delivers a frame each period, so every AoI is known
        seq = 0
        while not stop.is_set():
            now = clock.now_ms()
            for cam in range(1, N_CAMERAS + 1):
                bus.publish(KEYS.edge_frame(cam), encode_frame(
                    camera_id=cam, sequence=seq, generation_ms=now - 5.0,
                    scene_time_ms=now, camera=camera, image=image, delivery_ms=now))
            seq += 1
            time.sleep(period_ms / 1000.0)

    feeder = threading.Thread(target=feed, daemon=True)
    worker.start()
    feeder.start()
    t0 = time.perf_counter()
    rewards_first = None
    while time.perf_counter() - t0 < seconds:
        time.sleep(0.5)
        status = worker.learner.status()  # type: ignore[union-attr]
        if rewards_first is None and status.mean_reward is not None:
            rewards_first = status.mean_reward
    stop.set()
    status = worker.learner.status()  # type: ignore[union-attr]
    worker.stop()

    def value(name: str) -> float:
        return registry.get_sample_value(name) or 0.0

    n_updates = value("aoi3d_ppo_update_seconds_count")
    late = sorted(lateness_ms[5:])  # the first decisions include start-up
    result = {
        "benchmark": "scheduler online PPO learning",
        "seconds": seconds, "decision_period_ms": period_ms, "batch": batch,
        "torch_threads": threads, "cameras": N_CAMERAS,
        "decisions": len(lateness_ms),
        "decisions_skipped": value("aoi3d_decisions_skipped_total"),
        "lateness_ms": {"median": statistics.median(late),
                        "p99": late[int(0.99 * (len(late) - 1))], "max": late[-1]},
        "updates": n_updates,
        "update_ms_mean": 1000.0 * value("aoi3d_ppo_update_seconds_sum") / max(n_updates, 1),
        "episodes_learned": status.episodes_learned,
        "mean_reward_first_update": rewards_first,
        "mean_reward_last_update": status.mean_reward,
        "checkpoints_written": value("aoi3d_ppo_checkpoints_total"),
        "machine": {"python": platform.python_version(), "machine": platform.machine(),
                    "cpus": os.cpu_count(), "loadavg_1min": os.getloadavg()[0]},
    }
    common.write_json(common.RESULTS / "scheduler-learning.json", result)
    return result


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        result = run(args.seconds, args.period_ms, args.batch, args.threads)
        late = result["lateness_ms"]
        print(f"{result['decisions']} decisions in {result['seconds']:g} s, "
              f"{result['decisions_skipped']:g} skipped; lateness median {late['median']:.2f} ms, "
              f"p99 {late['p99']:.2f}, max {late['max']:.2f}; {result['updates']:g} updates of "
              f"{result['update_ms_mean']:.1f} ms; mean reward {result['mean_reward_first_update']}"
              f" → {result['mean_reward_last_update']}")
        print(f"written to {common.RESULTS / 'scheduler-learning.json'}")
    if args.json:
        common.print_json(result)


if __name__ == "__main__":
    main()
