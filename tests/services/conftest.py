"""The service tests' shared fixture: the dispatcher tests' scene (tests/support/dispatcher.py),
generated once per module that asks for ``dataset`` (a module may define its own)."""

import pytest

from aoi3d.scene import SceneDataset
from tests.support.dispatcher import trainer_scene


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    return trainer_scene(tmp_path_factory)
