"""PSNR before and after a ``kill -9`` of the trainer, with and without checkpoints.

Runs ``aoi3d up`` on the default scene with the warm carry (the continuously trained model
renders; with the default fresh carry every render trains a new model, so a restart loses
nothing to checkpoint), waits ``--train-s``, takes the mean PSNR of the last ``--window-s``,
kills the trainer, and reports the PSNR of the renders in the ``--window-s`` after the first
new one. Once with checkpoints every ``--period-s``, once without.

    python bench/trainer_restart.py            # JSON to bench/results/trainer_restart.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
OFFSET, ZENOH = 3000, 9457
METRICS = f"http://127.0.0.1:{8105 + OFFSET}"


def history() -> list[dict]:
    """Every scored render so far (the metrics service keeps the last 1000)."""
    return httpx.get(f"{METRICS}/quality", params={"limit": 100_000},
                     timeout=30).json()["history"]


def run(period_s: float, args: argparse.Namespace, log_dir: Path) -> dict:
    run_id = f"restart{int(period_s * 10)}"
    ckpt = ROOT / "runs" / "checkpoints" / f"{run_id}.trainer.pt"
    ckpt.unlink(missing_ok=True)
    env = dict(os.environ, AOI3D_TRAINER_CARRY="warm",
               AOI3D_TRAINER_CHECKPOINT_PERIOD_S=str(period_s))
    up = subprocess.Popen([sys.executable, "-m", "aoi3d", "up", "--run-id", run_id,
                           "--port-offset", str(OFFSET), "--zenoh-port", str(ZENOH),
                           "--log-dir", str(log_dir), "--quiet"], cwd=ROOT, env=env,
                          stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                          start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                if history():
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise SystemExit("no Quality within 180 s")
            time.sleep(1)
        time.sleep(args.train_s)
        before = [q["psnr_db"] for q in history()][-args.renders:]
        state = json.loads((log_dir / "latest" / "up.json").read_text())
        t_kill = time.time()
        os.kill(state["children"]["trainer"]["pid"], signal.SIGKILL)
        n_before = len(history())
        while len(history()) <= n_before:
            time.sleep(0.2)
        first_s = time.time() - t_kill
        while len(history()) < n_before + args.renders:
            time.sleep(0.5)
        after = [q["psnr_db"] for q in history()][n_before:n_before + args.renders]
        return {"checkpoint_period_s": period_s,
                "psnr_before_db": round(statistics.mean(before), 2),
                "psnr_after_db": round(statistics.mean(after), 2),
                "first_render_after_kill_s": round(first_s, 1),
                "renders_averaged": args.renders, "load_1min": os.getloadavg()[0]}
    finally:
        up.send_signal(signal.SIGTERM)
        up.wait(timeout=60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train-s", type=float, default=60.0)
    parser.add_argument("--renders", type=int, default=10)
    parser.add_argument("--period-s", type=float, default=5.0)
    parser.add_argument("--out", type=Path, default=ROOT / "bench/results/trainer_restart.json")
    args = parser.parse_args()
    log_dir = ROOT / "runs" / "bench-restart"
    results = [run(args.period_s, args, log_dir), run(0.0, args, log_dir)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": " ".join(sys.argv), "results": results},
                                   indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
