"""Zenoh over TLS (issue 24): a real router on 127.0.0.1 with certificates that
``deploy/secrets.sh`` (``make secrets``, openssl) makes in tmp_path. A session that has the CA
(and, with mutual TLS, a certificate the CA signed) joins and receives a published sample; a
session without the CA, with another CA, with a certificate of another CA, or on plain TCP
cannot open. The default (``aoi3d up``: tcp/127.0.0.1, no TLS key in the config) is unchanged.

Waits scale with AOI3D_TEST_TIMEOUT_SCALE, as in the other live tests."""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path

import pytest

from services.kit.settings import CommonSettings, zenoh_config
from services.router import RouterSettings, router_config
from tests.support.ports import block
from tests.support.timeouts import timeout_scale

ROOT = Path(__file__).resolve().parents[2]
SECRETS_SCRIPT = ROOT / "deploy" / "secrets.sh"
SCALE = timeout_scale()
_PORTS = block("zenoh-tls")
PORT = _PORTS.zenoh
"""Three ports of this file's own: PORT and the block's two extras."""


def make_secrets(folder: Path, **env: str) -> Path:
    subprocess.run([str(SECRETS_SCRIPT), str(folder)], check=True, capture_output=True,
                   env={**os.environ, **env}, timeout=60 * SCALE)
    return folder


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(ours, another): two folders as `make secrets` writes them, each with its own CA."""
    return (make_secrets(tmp_path_factory.mktemp("secrets")),
            make_secrets(tmp_path_factory.mktemp("other-secrets")))


def client(endpoint: str, *, ca: Path | None = None, cert: str | None = None,
           folder: Path | None = None, mtls: bool = False):
    """A client session on ``endpoint``; ``cert`` names zenoh_tls_<cert>_cert/_key in
    ``folder``. Raises zenoh.ZError when it cannot join within the scaled timeout."""
    import zenoh

    tls: dict[str, object] = {"zenoh_tls_root_ca": ca, "zenoh_tls_mtls": mtls}
    if cert is not None and folder is not None:
        tls |= {"zenoh_tls_cert": folder / f"zenoh_tls_{cert}_cert",
                "zenoh_tls_key": folder / f"zenoh_tls_{cert}_key"}
    conf = zenoh_config(CommonSettings(zenoh_connect=[endpoint], **tls))
    conf.insert_json5("connect/timeout_ms", json.dumps(int(2000 * SCALE)))
    return zenoh.open(conf)


@pytest.mark.parametrize("mtls", [False, True], ids=["tls", "mutual-tls"])
def test_a_client_with_the_ca_joins_and_one_without_cannot(pki, mtls: bool) -> None:
    import zenoh

    ours, other = pki
    port = _PORTS.extra(0) if mtls else PORT
    endpoint = f"tls/127.0.0.1:{port}"
    common = CommonSettings(zenoh_tls_root_ca=ours / "zenoh_tls_ca",
                            zenoh_tls_cert=ours / "zenoh_tls_router_cert",
                            zenoh_tls_key=ours / "zenoh_tls_router_key", zenoh_tls_mtls=mtls)
    conf = router_config(RouterSettings(listen=[endpoint]), common)
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is mtls
    router = zenoh.open(conf)
    try:
        good = {"ca": ours / "zenoh_tls_ca", "cert": "client", "folder": ours, "mtls": mtls}
        got: list[bytes] = []
        arrived = threading.Event()
        sub_session = client(endpoint, **good)
        sub = sub_session.declare_subscriber(
            "tls/t", lambda s: (got.append(s.payload.to_bytes()), arrived.set()))
        # the certificate names localhost too (SAN), as `make secrets` writes it
        pub_session = client(f"tls/localhost:{port}", **good)
        deadline = time.monotonic() + 10 * SCALE
        while not arrived.is_set() and time.monotonic() < deadline:
            pub_session.put("tls/t", b"hello")
            arrived.wait(0.2)
        assert got and got[0] == b"hello"

        refused = {
            "no CA (system roots only)": dict(good, ca=None, cert=None, mtls=False),
            "another CA": dict(good, ca=other / "zenoh_tls_ca", folder=other),
            "plain tcp": {"endpoint": f"tcp/127.0.0.1:{port}"},
        }
        if mtls:  # the router checks the session's certificate too
            refused |= {"a certificate of another CA": dict(good, folder=other),
                        "no certificate": dict(good, cert=None, mtls=False)}
        for what, kwargs in refused.items():
            kwargs = {"endpoint": endpoint, **kwargs}
            with pytest.raises(zenoh.ZError):
                client(**kwargs).close()
                pytest.fail(f"a client with {what} joined")
        sub.undeclare()
        sub_session.close()
        pub_session.close()
    finally:
        router.close()


def test_tls_with_user_and_password(pki, tmp_path: Path) -> None:
    """compose's combination: TLS and usrpwd; the password travels inside TLS, and a session
    with the CA but a wrong password is still refused."""
    import zenoh

    ours, _ = pki
    endpoint = f"tls/127.0.0.1:{_PORTS.extra(1)}"
    tls = {"zenoh_tls_root_ca": ours / "zenoh_tls_ca"}
    router = zenoh.open(router_config(
        RouterSettings(listen=[endpoint]),
        CommonSettings(zenoh_user="aoi3d", zenoh_password="s3cret",
                       zenoh_tls_cert=ours / "zenoh_tls_router_cert",
                       zenoh_tls_key=ours / "zenoh_tls_router_key", **tls),
        secrets_dir=tmp_path))
    try:
        def session(password: str):
            conf = zenoh_config(CommonSettings(zenoh_connect=[endpoint], zenoh_user="aoi3d",
                                               zenoh_password=password, **tls))
            conf.insert_json5("connect/timeout_ms", json.dumps(int(2000 * SCALE)))
            return zenoh.open(conf)

        session("s3cret").close()
        with pytest.raises(zenoh.ZError):
            session("wrong").close()
    finally:
        router.close()


def test_the_default_config_has_no_tls(monkeypatch) -> None:
    """`aoi3d up`'s default: tcp/127.0.0.1:7447, no TLS key set."""
    for var in [v for v in os.environ if v.startswith("AOI3D_ZENOH") or v == "AOI3D_ROUTER_LISTEN"]:
        monkeypatch.delenv(var)
    common = CommonSettings()
    assert common.zenoh_connect == ["tcp/127.0.0.1:7447"]
    assert common.zenoh_tls([]) == {}
    conf = zenoh_config(common)
    for key in ("root_ca_certificate", "listen_certificate", "connect_certificate"):
        assert json.loads(conf.get_json(f"transport/link/tls/{key}")) is None
    router = router_config(RouterSettings(), common)
    assert json.loads(router.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(router.get_json("transport/link/tls/listen_certificate")) is None


def test_tls_settings_that_cannot_work_are_clear_errors(pki, tmp_path: Path) -> None:
    ours, _ = pki
    cert, key = ours / "zenoh_tls_router_cert", ours / "zenoh_tls_router_key"
    with pytest.raises(ValueError, match="listener needs"):
        CommonSettings().zenoh_tls(["tls/127.0.0.1:7447"])
    with pytest.raises(ValueError, match="mutual TLS needs"):
        CommonSettings(zenoh_tls_mtls=True, zenoh_tls_cert=cert, zenoh_tls_key=key).zenoh_tls([])
    with pytest.raises(ValueError, match="go together"):
        CommonSettings(zenoh_tls_cert=cert).zenoh_tls([])
    with pytest.raises(ValueError, match="not a file"):
        CommonSettings(zenoh_tls_root_ca=tmp_path / "missing.pem").zenoh_tls([])


def test_make_secrets_certificates(tmp_path: Path) -> None:
    """One certificate per router name (+ localhost/127.0.0.1), signed by the CA, kept on a
    second run; a certificate the CA did not sign is made again."""
    folder = make_secrets(tmp_path / "s", AOI3D_ZENOH_ROUTERS="router,router-b",
                          AOI3D_ZENOH_TLS_SANS="IP:10.0.0.5")
    ca = folder / "zenoh_tls_ca"
    for name in ("router", "router-b", "client"):
        subprocess.run(["openssl", "verify", "-CAfile", str(ca),
                        str(folder / f"zenoh_tls_{name}_cert")], check=True, capture_output=True)
    text = subprocess.run(["openssl", "x509", "-noout", "-ext", "subjectAltName", "-in",
                           str(folder / "zenoh_tls_router-b_cert")],
                          check=True, capture_output=True, text=True).stdout
    for san in ("DNS:router-b", "DNS:localhost", "IP Address:127.0.0.1", "IP Address:10.0.0.5"):
        assert san in text, text
    assert oct((folder / "zenoh_tls_ca_key").stat().st_mode & 0o777) == "0o600"
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    make_secrets(folder, AOI3D_ZENOH_ROUTERS="router,router-b")
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    other = make_secrets(tmp_path / "o")
    for name in ("router", "router-edge", "router-a", "router-b"):  # both compose files'
        assert (other / f"zenoh_tls_{name}_cert").is_file()
    foreign = (other / "zenoh_tls_router_cert").read_bytes()
    (folder / "zenoh_tls_router_cert").write_bytes(foreign)
    make_secrets(folder)
    assert (folder / "zenoh_tls_router_cert").read_bytes() != foreign
    subprocess.run(["openssl", "verify", "-CAfile", str(ca),
                    str(folder / "zenoh_tls_router_cert")], check=True, capture_output=True)
