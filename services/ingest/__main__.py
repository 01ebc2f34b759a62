"""``python -m services.ingest``: real cameras in (the rig file ``AOI3D_RIG``; settings from the
environment). A rig file that cannot be used is one error per bad field and exit status 2."""

import logging
import sys

from aoi3d.rigfile import RigError, load_rig
from services.ingest.app import create_app
from services.ingest.settings import Settings
from services.kit.app import serve
from services.kit.observe import setup_logging

if __name__ == "__main__":
    settings = Settings()
    setup_logging(settings.common.log_level, "ingest")
    if settings.common.rig is None:
        logging.getLogger("ingest").error("no rig file: set AOI3D_RIG (aoi3d up --rig does)")
        sys.exit(2)
    try:
        rig = load_rig(settings.common.rig)
    except RigError as err:
        logging.getLogger("ingest").error("%s", err)
        sys.exit(2)
    serve(create_app(settings, rig=rig), settings)
