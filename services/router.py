"""A local Zenoh router: ``python -m services.router``.

No zenohd binary ships with PyPI or Debian; a Python session in router mode is a working
router. Multicast scouting is off; it listens only on the configured endpoints
(``AOI3D_ROUTER_LISTEN``, default ``tcp/127.0.0.1:7447``; ``tls/host:port`` with
``AOI3D_ZENOH_TLS_CERT``/``_KEY``, as compose.yaml runs it).
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

from services.kit.ports import ZENOH_PORT
from services.kit.settings import CommonSettings, Endpoints, _split_endpoints, insert_tls

log = logging.getLogger("aoi3d.router")


class RouterSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="AOI3D_ROUTER_", extra="ignore")

    listen: Endpoints = Field(default_factory=lambda: [f"tcp/127.0.0.1:{ZENOH_PORT}"],
                              description="Endpoints the router listens on.")
    connect: Endpoints = Field(
        default_factory=list,
        description="Other routers this one connects to (comma-separated): a mesh of hosts, "
                    "each with its own router (compose.multihost.yaml). Zenoh retries a "
                    "lost link by itself.")
    log_level: str = Field("INFO", description="Python logging level.")

    _split = field_validator("listen", "connect", mode="before")(
        classmethod(lambda cls, v: _split_endpoints(v)))


def router_config(settings: RouterSettings, common: CommonSettings | None = None,
                  secrets_dir: Path | None = None):
    """The router's Zenoh config. With Zenoh credentials configured (``AOI3D_ZENOH_USER`` and
    a password, as the services read them) it accepts only sessions that present them: the
    usrpwd dictionary is written, readable by this user only, to ``secrets_dir`` (a fresh
    temporary folder by default). On ``tls/`` endpoints it presents ``AOI3D_ZENOH_TLS_CERT``
    (and with ``AOI3D_ZENOH_TLS_MTLS`` accepts only sessions whose certificate the root CA
    signed)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    common = common or CommonSettings()
    credentials = common.zenoh_credentials()
    if credentials is not None:
        user, password = credentials
        folder = secrets_dir or Path(tempfile.mkdtemp(prefix="aoi3d-router-"))
        dictionary = folder / "zenoh-users"
        dictionary.touch(mode=0o600)
        dictionary.write_text(f"{user}:{password}\n")
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(dictionary)))
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    insert_tls(conf, common.zenoh_tls(settings.listen))
    return conf


def main() -> None:
    import zenoh

    settings = RouterSettings()
    logging.basicConfig(level=settings.log_level.upper(),
                        format="%(asctime)s router %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    common = CommonSettings()
    with zenoh.open(router_config(settings, common)) as session:
        guards = [*(["user/password authentication"] if common.zenoh_credentials() else []),
                  *(["mutual TLS"] if common.zenoh_tls_mtls else
                    ["TLS"] if any(e.startswith("tls/") for e in settings.listen) else [])]
        log.info("Zenoh router %s listening on %s%s", session.zid(), ", ".join(settings.listen),
                 f" ({', '.join(guards)})" if guards else "")
        stop.wait()
        log.info("router stopping")


if __name__ == "__main__":
    main()
