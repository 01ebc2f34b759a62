"""``python -m services.trainer``: run the trainer service (settings from the environment)."""

from __future__ import annotations

from services.kit.app import serve
from services.kit.observe import setup_logging
from services.trainer.app import create_app
from services.trainer.settings import Settings


def main() -> None:
    settings = Settings()
    setup_logging(settings.common.log_level, "trainer")
    serve(create_app(settings), settings)


if __name__ == "__main__":
    main()
