"""``python -m services.recorder``: run the recorder service (settings from the environment)."""

from services.kit.app import run_service
from services.recorder.app import create_app
from services.recorder.settings import Settings

if __name__ == "__main__":
    run_service("recorder", Settings, create_app)
