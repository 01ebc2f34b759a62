"""``python -m services.camera``: run the camera service (settings from the environment)."""

from services.camera.app import create_app
from services.camera.settings import Settings
from services.kit.app import run_service

if __name__ == "__main__":
    run_service("camera", Settings, create_app, dataset="frames")
