"""The unit tests' shared fixture: the tiny scene (tests/support/tiny.py), generated once per module
that asks for ``dataset``."""

import pytest

from aoi3d.scene import SceneDataset
from tests.support.tiny import tiny_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    return tiny_dataset(tmp_path_factory.mktemp("scene") / "tiny")
