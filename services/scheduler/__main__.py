"""``python -m services.scheduler``: run the scheduler service (settings from the environment)."""

from __future__ import annotations

from services.kit.app import serve
from services.kit.observe import setup_logging
from services.scheduler.app import create_app
from services.scheduler.settings import Settings


def main() -> None:
    settings = Settings()
    setup_logging(settings.common.log_level, "scheduler")
    serve(create_app(settings), settings)


if __name__ == "__main__":
    main()
