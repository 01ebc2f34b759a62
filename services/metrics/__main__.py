"""``python -m services.metrics``: run the metrics service (settings from the environment)."""

from services.kit.app import run_service
from services.metrics.app import create_app
from services.metrics.settings import Settings


def _torch_threads(settings: Settings) -> None:
    """LPIPS runs on this process's torch threads; one keeps it off the dispatcher's cores."""
    if settings.torch_threads:
        import torch

        torch.set_num_threads(settings.torch_threads)


if __name__ == "__main__":
    run_service("metrics", Settings, create_app, prepare=_torch_threads)
