"""``python -m services.scheduler``: run the scheduler service (settings from the environment)."""

from services.kit.app import run_service
from services.scheduler.app import create_app
from services.scheduler.settings import Settings


def _torch_threads(settings: Settings) -> None:
    """A ppo policy acts and learns on this process's torch threads; its network is tiny, so
    one thread is fastest and leaves the cores to the dispatcher."""
    if settings.torch_threads:
        import torch

        torch.set_num_threads(settings.torch_threads)


if __name__ == "__main__":
    run_service("scheduler", Settings, create_app, prepare=_torch_threads)
