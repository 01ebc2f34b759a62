"""``python -m services.trainer``: run the trainer service (settings from the environment)."""

from services.kit.app import run_service
from services.trainer.app import create_app
from services.trainer.settings import Settings


def _configure_process(settings: Settings) -> None:
    """The process-wide settings of a training process (the field's constructor makes none):
    torch threads (0 keeps torch's default) and the allocator tuned for training."""
    from aoi3d.field.process import configure_process

    configure_process(settings.torch_threads or None)


if __name__ == "__main__":
    run_service("trainer", Settings, create_app, prepare=_configure_process, dataset="metadata")
