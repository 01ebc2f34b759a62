"""``python -m services.dispatcher``: run the pool's dispatcher (settings from the
environment). It trains nothing itself: reconstruction workers (``python -m services.recon``)
do. With a rig file (``AOI3D_RIG``: real cameras) it reads no dataset."""

from services.dispatcher.app import create_app
from services.dispatcher.settings import OLD_PREFIX, Settings
from services.kit.app import run_service
from services.kit.renamed import renamed_variables, warn_renamed
from services.kit.settings import CommonSettings


def _warn_old_names(settings: Settings) -> None:
    """One deprecation line naming each ``AOI3D_TRAINER_`` variable that was read."""
    warn_renamed("services.dispatcher", renamed_variables(OLD_PREFIX, "AOI3D_DISPATCHER_"))


if __name__ == "__main__":
    real = CommonSettings().rig is not None
    run_service("dispatcher", Settings, create_app, _warn_old_names,
                dataset=None if real else "metadata")
