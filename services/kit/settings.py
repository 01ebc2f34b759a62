"""Settings shared by every service (env prefix ``AOI3D_``) and the Zenoh config built from them.

Each service adds its own ``Settings`` with a per-service prefix (``AOI3D_CAMERA_`` …) and
holds a ``CommonSettings`` for what all processes of one run must agree on.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from services.kit.ports import ZENOH_PORT

Endpoints = Annotated[list[str], NoDecode]


def _split_endpoints(value: object) -> object:
    """Accept a JSON list or a comma-separated string (friendlier in compose files)."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            return json.loads(text)
        return [part.strip() for part in text.split(",") if part.strip()]
    return value


class CommonSettings(BaseSettings):
    """What every process of one run shares. Environment variables: ``AOI3D_<FIELD>``."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_", extra="ignore")

    run_id: str = Field("default", pattern=r"^[A-Za-z0-9_\-]+$",
                        description="Run id: the <run> segment of every key expression.")
    zenoh_mode: Literal["client", "peer"] = Field(
        "client", description="Zenoh session mode of the services (the router is separate).")
    zenoh_connect: Endpoints = Field(
        default_factory=lambda: [f"tcp/127.0.0.1:{ZENOH_PORT}"],
        description="Zenoh endpoints to connect to (comma-separated or JSON list).")
    zenoh_listen: Endpoints = Field(default_factory=list,
                                    description="Zenoh endpoints to listen on (peer mode).")
    sites: Endpoints = Field(
        default_factory=lambda: ["site1"],
        description="The run's sites (a turbine each: its own cameras, channel, policy and "
                    "quality; one shared pool of reconstruction workers), comma-separated. Each "
                    "service serves every site; its REST paths address the first one, "
                    "/sites/<site>/… any of them.")
    cameras: int = Field(18, ge=1, le=256,
                         description="Training cameras N (ids 1..N; id 0 is the held-out view).")
    time_scale: float = Field(0.1, gt=0, le=10,
                              description="Simulation seconds per wall second (shared clock).")
    epoch_s: float = Field(0.0, ge=0,
                           description="Wall time (Unix s) at which simulation time is 0.")
    dataset: Path = Field(Path("data/turbine-rotor"), description=(
        "Scene dataset folder (the rotor close-up, `aoi3d scene generate --framing rotor "
        "--rotor-rpm 6`; any layout `aoi3d scene info` reads)."))
    rig: Path | None = Field(None, description=(
        "A rig file of real cameras (ROS 2 over Zenoh; docs/real-cameras.md): the ingest "
        "service takes their frames where the camera emulator would publish, and the dispatcher "
        "renders the rig's view in the rig's scene box instead of the dataset's. Set by `aoi3d "
        "up --rig`. Unset: the emulated cameras of AOI3D_DATASET."))
    log_level: str = Field("INFO", description="Python logging level.")
    max_skew_s: float = Field(
        0.5, gt=0, le=60,
        description="Clock disagreement tolerated between services (wall seconds): a bus "
                    "message stamped further ahead of the receiver's clock than this (in sim "
                    "time: this × time scale) is rejected and counted as clock_skew.")
    zenoh_user: str | None = Field(
        None, description="Zenoh user name: with a password, every session authenticates to "
                          "the router (usrpwd), and a router given them accepts only sessions "
                          "that present them. Unset: no authentication.")
    zenoh_password: SecretStr | None = Field(None, description="Zenoh password (with "
                                                               "AOI3D_ZENOH_USER).")
    zenoh_password_file: Path | None = Field(
        None, description="A file holding the Zenoh password (compose secrets); wins over "
                          "AOI3D_ZENOH_PASSWORD.")
    zenoh_tls_root_ca: Path | None = Field(
        None, description="Zenoh TLS: the CA certificate (PEM) a session checks the router's "
                          "certificate against on `tls/` endpoints (name or IP of the endpoint "
                          "must be in its SANs); with mutual TLS the router checks the "
                          "sessions' certificates against it too. Unset: plain `tcp/` only.")
    zenoh_tls_cert: Path | None = Field(
        None, description="Zenoh TLS: this process's certificate (PEM, signed by the CA): a "
                          "`tls/` listener (the router) presents it; with mutual TLS a "
                          "connecting session presents it too.")
    zenoh_tls_key: Path | None = Field(
        None, description="Zenoh TLS: the private key (PEM) of AOI3D_ZENOH_TLS_CERT.")
    zenoh_tls_mtls: bool = Field(
        False, description="Zenoh mutual TLS: the router accepts only sessions that present a "
                           "certificate signed by AOI3D_ZENOH_TLS_ROOT_CA, and sessions "
                           "present AOI3D_ZENOH_TLS_CERT.")
    stall_s: float = Field(
        30.0, gt=0, le=3600,
        description="Readiness that tells the truth: a service alive but not doing its job for "
                    "this many wall seconds answers /readyz with 503 and the reason (scheduler: "
                    "no frame delivered; dispatcher: decisions arrive but no training step; "
                    "metrics: no Quality).")
    control_token: SecretStr | None = Field(
        None, description="Bearer token every state-changing REST request (PUT/POST/PATCH/"
                          "DELETE) must carry as `Authorization: Bearer <token>` (401 without "
                          "it); GETs stay open. Unset: control is open (loopback only, as by "
                          "default).")
    control_token_file: Path | None = Field(
        None, description="A file holding the control token (compose secrets); wins over "
                          "AOI3D_CONTROL_TOKEN.")
    allowed_hosts: Endpoints = Field(
        default_factory=lambda: ["127.0.0.1", "localhost", "::1"],
        description="Host names the REST APIs answer to (the Host header, and the Origin of "
                    "state-changing requests): others get 400/403, which stops DNS rebinding "
                    "and cross-site requests. Comma-separated; `*` allows any.")
    max_body_bytes: int = Field(
        64 * 1024, ge=1024, le=64 * 1024 * 1024,
        description="Largest REST request body accepted (413 beyond).")
    files_roots: Endpoints = Field(
        default_factory=lambda: ["runs", "models"],
        description="Folders (relative to the working directory, or absolute) that file paths "
                    "in REST requests (a PPO checkpoint, save_to) must lie in; others are 422.")

    def zenoh_credentials(self) -> tuple[str, str] | None:
        """(user, password) when Zenoh authentication is configured, else None."""
        if self.zenoh_password_file is not None:
            password: str | None = self.zenoh_password_file.read_text().strip()
        else:
            password = (self.zenoh_password.get_secret_value()
                        if self.zenoh_password is not None else None)
        if not self.zenoh_user and not password:
            return None
        if not (self.zenoh_user and password):
            raise ValueError("Zenoh authentication needs both AOI3D_ZENOH_USER and a password "
                             "(AOI3D_ZENOH_PASSWORD or AOI3D_ZENOH_PASSWORD_FILE)")
        return self.zenoh_user, password

    def zenoh_tls(self, listen: list[str]) -> dict[str, object]:
        """The ``transport/link/tls`` keys of a Zenoh config listening on ``listen`` ({} when no
        TLS setting is given). A clear error when a ``tls/`` listener lacks its certificate
        and key, or mutual TLS lacks one of its three files."""
        files = {"root_ca_certificate": self.zenoh_tls_root_ca,
                 "listen_certificate": self.zenoh_tls_cert,
                 "listen_private_key": self.zenoh_tls_key}
        if self.zenoh_tls_mtls:
            files |= {"connect_certificate": self.zenoh_tls_cert,
                      "connect_private_key": self.zenoh_tls_key}
        if self.zenoh_tls_mtls and None in files.values():
            raise ValueError("Zenoh mutual TLS needs AOI3D_ZENOH_TLS_ROOT_CA, "
                             "AOI3D_ZENOH_TLS_CERT and AOI3D_ZENOH_TLS_KEY")
        if (any(e.startswith("tls/") for e in listen)
                and (self.zenoh_tls_cert is None or self.zenoh_tls_key is None)):
            raise ValueError("a Zenoh tls/ listener needs AOI3D_ZENOH_TLS_CERT and "
                             "AOI3D_ZENOH_TLS_KEY")
        if (self.zenoh_tls_cert is None) != (self.zenoh_tls_key is None):
            raise ValueError("AOI3D_ZENOH_TLS_CERT and AOI3D_ZENOH_TLS_KEY go together")
        out: dict[str, object] = {key: str(path) for key, path in files.items()
                                  if path is not None}
        for path in {p for p in files.values() if p is not None}:
            if not path.is_file():
                raise ValueError(f"Zenoh TLS: {path} is not a file")
        if out:
            out["enable_mtls"] = self.zenoh_tls_mtls
        return out

    def token(self) -> str | None:
        """The control token in force (from the file when one is named), None when open."""
        if self.control_token_file is not None:
            text = self.control_token_file.read_text().strip()
            return text or None
        if self.control_token is not None:
            return self.control_token.get_secret_value() or None
        return None

    @property
    def skew_ms(self) -> float:
        """:attr:`max_skew_s` in sim milliseconds."""
        return self.max_skew_s * 1000.0 * self.time_scale

    _split = field_validator("zenoh_connect", "zenoh_listen", "allowed_hosts", "files_roots",
                             "sites", mode="before")(
        classmethod(lambda cls, v: _split_endpoints(v)))

    @field_validator("sites")
    @classmethod
    def _check_sites(cls, value: list[str]) -> list[str]:
        from services.kit.keys import check_site

        if not value:
            raise ValueError("at least one site")
        if len(set(value)) != len(value):
            raise ValueError(f"site names must differ: {value}")
        if len(value) > 64:
            raise ValueError(f"at most 64 sites, got {len(value)}")
        return [check_site(v) for v in value]


class ServiceSettings(BaseSettings):
    """Base of each service's settings: where its REST API listens."""

    model_config = SettingsConfigDict(extra="ignore")

    host: str = Field("127.0.0.1", description="Address the REST API binds to.")
    port: int = Field(0, ge=0, le=65535, description="REST API port.")
    common: CommonSettings = Field(default_factory=CommonSettings)


def zenoh_config(common: CommonSettings, *, mode: str | None = None,
                 listen: list[str] | None = None, connect: list[str] | None = None):
    """Build a ``zenoh.Config``: explicit endpoints, multicast scouting off, usrpwd and TLS
    when configured (``tls/`` endpoints need :attr:`CommonSettings.zenoh_tls_root_ca`)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode or common.zenoh_mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conn = common.zenoh_connect if connect is None else connect
    lst = common.zenoh_listen if listen is None else listen
    if conn:
        conf.insert_json5("connect/endpoints", json.dumps(conn))
    if lst:
        conf.insert_json5("listen/endpoints", json.dumps(lst))
    credentials = common.zenoh_credentials()
    if credentials is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(credentials[0]))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(credentials[1]))
    insert_tls(conf, common.zenoh_tls(lst))
    return conf


def insert_tls(conf, tls: dict[str, object]) -> None:
    """Write :meth:`CommonSettings.zenoh_tls`'s keys under ``transport/link/tls`` (Zenoh's own
    names: a misspelt key raises)."""
    for key, value in tls.items():
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))


def repo_root() -> Path:
    return Path(__file__).resolve().parents[2]
