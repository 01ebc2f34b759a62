"""Zenoh user/password authentication (issue 11): a real router on 127.0.0.1 configured with
credentials lets a session that presents them publish and subscribe, and refuses sessions
with a wrong password or none."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from services.kit.settings import CommonSettings, zenoh_config
from services.router import RouterSettings, router_config
from tests.support.ports import block
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()
PORT = block("zenoh-auth").zenoh
ENDPOINT = f"tcp/127.0.0.1:{PORT}"


def session(**credentials):
    import zenoh

    conf = zenoh_config(CommonSettings(zenoh_connect=[ENDPOINT], **credentials))
    conf.insert_json5("connect/timeout_ms", json.dumps(int(2000 * SCALE)))
    return zenoh.open(conf)


def test_only_sessions_with_the_credentials_reach_the_router(tmp_path: Path) -> None:
    import zenoh

    secret = tmp_path / "zenoh-password"
    secret.write_text("s3cret\n")
    common = CommonSettings(zenoh_user="aoi3d", zenoh_password_file=secret)
    router = zenoh.open(router_config(RouterSettings(listen=[ENDPOINT]), common,
                                      secrets_dir=tmp_path))
    try:
        assert oct((tmp_path / "zenoh-users").stat().st_mode & 0o777) == "0o600"
        got: list[bytes] = []
        arrived = threading.Event()
        sub_session = session(zenoh_user="aoi3d", zenoh_password_file=secret)
        sub = sub_session.declare_subscriber(
            "auth/t", lambda s: (got.append(s.payload.to_bytes()), arrived.set()))
        pub_session = session(zenoh_user="aoi3d", zenoh_password="s3cret")
        deadline = time.monotonic() + 10 * SCALE
        while not arrived.is_set() and time.monotonic() < deadline:
            pub_session.put("auth/t", b"hello")
            arrived.wait(0.2)
        assert got and got[0] == b"hello"
        for creds in ({"zenoh_user": "aoi3d", "zenoh_password": "wrong"}, {}):
            with pytest.raises(zenoh.ZError):
                session(**creds)
        sub.undeclare()
        sub_session.close()
        pub_session.close()
    finally:
        router.close()


def test_a_user_without_a_password_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="needs both"):
        CommonSettings(zenoh_user="aoi3d").zenoh_credentials()
