"""A local Zenoh router: ``python -m services.router``.

No zenohd binary ships with PyPI or Debian; a Python session in router mode is a working
router. Multicast scouting is off; it listens only on the configured endpoints
(``AOI3D_ROUTER_LISTEN``, default ``tcp/127.0.0.1:7447``).
"""

from __future__ import annotations

import json
import logging
import signal
import tempfile
import threading
from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.kit.settings import CommonSettings, Endpoints, _split_endpoints

log = logging.getLogger("aoi3d.router")


class RouterSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="AOI3D_ROUTER_", extra="ignore")

    listen: Endpoints = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                              description="Endpoints the router listens on.")
    log_level: str = Field("INFO", description="Python logging level.")

    _split = field_validator("listen", mode="before")(
        classmethod(lambda cls, v: _split_endpoints(v)))


def router_config(settings: RouterSettings, common: CommonSettings | None = None,
                  secrets_dir: Path | None = None):
    """The router's Zenoh config. With Zenoh credentials configured (``AOI3D_ZENOH_USER`` and
    a password, as the services read them) it accepts only sessions that present them: the
    usrpwd dictionary is written, readable by this user only, to ``secrets_dir`` (a fresh
    temporary folder by default)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    credentials = (common or CommonSettings()).zenoh_credentials()
    if credentials is not None:
        user, password = credentials
        folder = secrets_dir or Path(tempfile.mkdtemp(prefix="aoi3d-router-"))
        dictionary = folder / "zenoh-users"
        dictionary.touch(mode=0o600)
        dictionary.write_text(f"{user}:{password}\n")
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(dictionary)))
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
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
        log.info("Zenoh router %s listening on %s%s", session.zid(), ", ".join(settings.listen),
                 " (user/password authentication)"
                 if CommonSettings().zenoh_credentials() else "")
        stop.wait()
        log.info("router stopping")


if __name__ == "__main__":
    main()
