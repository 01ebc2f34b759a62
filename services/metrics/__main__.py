"""``python -m services.metrics``: run the metrics service (settings from the environment)."""

from __future__ import annotations

from services.kit.app import serve
from services.kit.observe import setup_logging
from services.metrics.app import create_app
from services.metrics.settings import Settings


def main() -> None:
    settings = Settings()
    setup_logging(settings.common.log_level, "metrics")
    if settings.torch_threads:
        import torch

        torch.set_num_threads(settings.torch_threads)
    serve(create_app(settings), settings)


if __name__ == "__main__":
    main()
