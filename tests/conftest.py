"""Suite-wide settings and fixtures.

FastAPI's TestClient sends ``Host: testserver``, which the REST guard (services.kit.guard) must
accept in tests as it accepts 127.0.0.1 and localhost. ``small_dataset``: the live tests' scene
(tests/support/pipeline.py), generated once per module that asks for it."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("AOI3D_ALLOWED_HOSTS", "127.0.0.1,localhost,::1,testserver")


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tests.support.pipeline import small_scene

    return small_scene(tmp_path_factory)
