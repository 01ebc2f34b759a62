"""A local Zenoh router: ``python -m services.router``.

No zenohd binary ships with PyPI or Debian; a Python session in router mode is a working
router. Multicast scouting is off; it listens only on the configured endpoints
(``AOI3D_ROUTER_LISTEN``, default ``tcp/127.0.0.1:7447``).
"""

from __future__ import annotations

import json
import logging
import signal
import threading

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.kit.settings import Endpoints, _split_endpoints

log = logging.getLogger("aoi3d.router")


class RouterSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="AOI3D_ROUTER_", extra="ignore")

    listen: Endpoints = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                              description="Endpoints the router listens on.")
    log_level: str = Field("INFO", description="Python logging level.")

    _split = field_validator("listen", mode="before")(
        classmethod(lambda cls, v: _split_endpoints(v)))


def router_config(settings: RouterSettings):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    return conf


def main() -> None:
    import zenoh

    settings = RouterSettings()
    logging.basicConfig(level=settings.log_level.upper(),
                        format="%(asctime)s router %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with zenoh.open(router_config(settings)) as session:
        log.info("Zenoh router %s listening on %s", session.zid(), ", ".join(settings.listen))
        stop.wait()
        log.info("router stopping")


if __name__ == "__main__":
    main()
