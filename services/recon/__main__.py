"""``python -m services.recon``: run one reconstruction worker (settings from the environment)
until SIGINT/SIGTERM."""

from __future__ import annotations

import signal
import threading

from aoi3d.device import resolve_device
from aoi3d.field.process import configure_process
from services.kit.bus import ZenohBus
from services.kit.observe import setup_logging
from services.kit.settings import zenoh_config
from services.recon.core import ReconCore
from services.recon.settings import Settings
from services.recon.worker import ReconWorker, default_worker_id


def main() -> None:
    settings = Settings()
    setup_logging(settings.common.log_level, "recon")
    configure_process(settings.torch_threads or None)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    core = ReconCore(worker_id=settings.worker_id or default_worker_id(),
                     device=resolve_device(settings.device),
                     num_threads=settings.torch_threads)
    bus = ZenohBus(zenoh_config(settings.common))
    try:
        ReconWorker(settings, bus, core).run(stop)
    finally:
        bus.close()


if __name__ == "__main__":
    main()
