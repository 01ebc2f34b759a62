"""``python -m services.viewer``: run the 3D viewer (settings from the environment). With a rig
file (``AOI3D_RIG``: real cameras) it reads no dataset: the rig's cameras, view and box."""

from services.kit.app import run_service
from services.kit.renamed import renamed_variables, warn_renamed
from services.kit.settings import CommonSettings
from services.viewer.app import create_app
from services.viewer.settings import Settings


def _warn_old_names(settings: Settings) -> None:
    """One deprecation line when the dispatcher's URL came under its old name."""
    warn_renamed("services.viewer", renamed_variables("AOI3D_VIEWER_TRAINER_URL",
                                                      "AOI3D_VIEWER_DISPATCHER_URL"))


if __name__ == "__main__":
    real = CommonSettings().rig is not None
    run_service("viewer", Settings, create_app, _warn_old_names,
                dataset=None if real else "metadata")
