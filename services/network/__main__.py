"""``python -m services.network``: run the network service (settings from the environment)."""

from services.kit.app import run_service
from services.network.app import create_app
from services.network.settings import Settings

if __name__ == "__main__":
    run_service("network", Settings, create_app)
