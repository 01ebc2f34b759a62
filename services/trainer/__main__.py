"""``python -m services.trainer``: run the trainer service (settings from the environment)."""

from services.kit.app import run_service
from services.trainer.app import create_app
from services.trainer.settings import Settings

if __name__ == "__main__":
    from aoi3d.field.process import configure_process

    # the process-wide settings of a training process (the field's constructor makes none)
    configure_process(Settings().torch_threads or None)
    run_service("trainer", Settings, create_app, dataset="metadata")
