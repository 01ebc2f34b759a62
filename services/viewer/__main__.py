"""``python -m services.viewer``: run the 3D viewer (settings from the environment). With a rig
file (``AOI3D_RIG``: real cameras) it reads no dataset: the rig's cameras, view and box."""

from services.kit.app import run_service
from services.kit.settings import CommonSettings
from services.viewer.app import create_app
from services.viewer.settings import Settings

if __name__ == "__main__":
    real = CommonSettings().rig is not None
    run_service("viewer", Settings, create_app, dataset=None if real else "metadata")
