"""``python -m services.camera``: run the camera service (settings from the environment)."""

from __future__ import annotations

from services.camera.app import create_app
from services.camera.settings import Settings
from services.kit.app import serve
from services.kit.observe import setup_logging


def main() -> None:
    settings = Settings()
    setup_logging(settings.common.log_level, "camera")
    serve(create_app(settings), settings)


if __name__ == "__main__":
    main()
