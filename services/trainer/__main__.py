"""``python -m services.trainer``: run the trainer service, the pool's dispatcher (settings from
the environment). It trains nothing itself: reconstruction workers (``python -m
services.recon``) do. With a rig file (``AOI3D_RIG``: real cameras) it reads no dataset."""

from services.kit.app import run_service
from services.kit.settings import CommonSettings
from services.trainer.app import create_app
from services.trainer.settings import Settings

if __name__ == "__main__":
    real = CommonSettings().rig is not None
    run_service("trainer", Settings, create_app, dataset=None if real else "metadata")
