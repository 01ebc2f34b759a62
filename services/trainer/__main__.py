"""``python -m services.trainer``: run the trainer service (settings from the environment)."""

from services.kit.app import run_service
from services.trainer.app import create_app
from services.trainer.settings import Settings

if __name__ == "__main__":
    run_service("trainer", Settings, create_app, dataset="metadata")
