"""``python -m services.console``: run the console (settings from the environment)."""

from services.console.app import create_app
from services.console.settings import Settings
from services.kit.app import run_service

if __name__ == "__main__":
    run_service("console", Settings, create_app)
