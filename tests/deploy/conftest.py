"""Fixtures of the deploy tests: compose.yaml and the Compose Specification's schema."""

from __future__ import annotations

import json
from typing import Any

import pytest

from tests.support.compose_checks import COMPOSE_FILE, SCHEMA_FILE
from tests.support.compose_file import _yaml


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return _yaml(COMPOSE_FILE)


@pytest.fixture(scope="module")
def schema() -> dict[str, Any]:
    return json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))
