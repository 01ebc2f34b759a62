"""``python -m services.recon``: run one reconstruction worker (settings from the environment)
until SIGINT/SIGTERM."""

from __future__ import annotations

import signal

from aoi3d.device import resolve_device
from aoi3d.field.process import configure_process
from services.kit.bus import ZenohBus
from services.kit.observe import setup_logging
from services.kit.runtime import Loops
from services.kit.settings import zenoh_config
from services.recon.core import ReconCore
from services.recon.runtime import ReconWorker, default_worker_id
from services.recon.settings import Settings


def main() -> None:
    settings = Settings()
    setup_logging(settings.common.log_level, "recon")
    configure_process(settings.torch_threads or None)
    core = ReconCore(worker_id=settings.worker_id or default_worker_id(),
                     device=resolve_device(settings.device),
                     num_threads=settings.torch_threads)
    bus = ZenohBus(zenoh_config(settings.common))
    loops = Loops("recon")
    loops.thread("jobs", ReconWorker(settings, bus, core).run)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: loops.stop_event.set())
    loops.start()
    while loops.not_running() is None and not loops.wait(0.5):
        pass
    # closing the session ends a request in flight (and with it the liveliness token) at
    # once, instead of after its wait; a job in progress is lost, as with any exit
    loops.stop_event.set()
    bus.close()
    loops.stop(timeout_s=5.0)


if __name__ == "__main__":
    main()
