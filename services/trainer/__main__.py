"""``python -m services.trainer``: run the trainer service, the pool's dispatcher (settings from
the environment). It trains nothing itself: reconstruction workers (``python -m
services.recon``) do."""

from services.kit.app import run_service
from services.trainer.app import create_app
from services.trainer.settings import Settings

if __name__ == "__main__":
    run_service("trainer", Settings, create_app, dataset="metadata")
