"""``python -m services.scheduler``: run the scheduler service (settings from the environment)."""

from services.kit.app import run_service
from services.scheduler.app import create_app
from services.scheduler.settings import Settings

if __name__ == "__main__":
    run_service("scheduler", Settings, create_app)
