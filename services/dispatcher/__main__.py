"""``python -m services.dispatcher``: run the pool's dispatcher (settings from the
environment). It trains nothing itself: reconstruction workers (``python -m services.recon``)
do. With a rig file (``AOI3D_RIG``: real cameras) it reads no dataset."""

import logging

from services.dispatcher.app import create_app
from services.dispatcher.settings import OLD_PREFIX, Settings, deprecated_names
from services.kit.app import run_service
from services.kit.settings import CommonSettings


def _warn_old_names(settings: Settings) -> None:
    """One deprecation line naming each ``AOI3D_TRAINER_`` variable that was read."""
    old = deprecated_names()
    if old:
        logging.getLogger("services.dispatcher").warning(
            "deprecated: %s read as %s; the %s names go in the next release", ", ".join(old),
            ", ".join("AOI3D_DISPATCHER_" + k[len(OLD_PREFIX):] for k in old), OLD_PREFIX)


if __name__ == "__main__":
    real = CommonSettings().rig is not None
    run_service("dispatcher", Settings, create_app, _warn_old_names,
                dataset=None if real else "metadata")
