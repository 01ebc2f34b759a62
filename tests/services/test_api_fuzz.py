"""Every REST operation of the five services fuzzed from its own OpenAPI (schemathesis, over
HTTP against the real apps served by uvicorn on 127.0.0.1, with a MemoryBus): no input,
valid (positive) or not (negative cases), gets a 5xx (issue 11). The number
of examples per operation is bounded (AOI3D_FUZZ_EXAMPLES, 15 by default) to keep the suite
quick; raise it for a deeper run."""

from __future__ import annotations

import itertools
import os
import socket
import threading
import time

import pytest
import schemathesis
import uvicorn
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis.checks import not_a_server_error

from aoi3d.scene import SceneDataset
from tests.support.guard import SERVICES, build
from tests.support.timeouts import timeout_scale

EXAMPLES = int(os.environ.get("AOI3D_FUZZ_EXAMPLES", "15"))
SCALE = timeout_scale()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("service", SERVICES)
def test_no_operation_answers_a_server_error(service: str,
                                             dataset: SceneDataset) -> None:
    app = build(service, dataset)
    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning", access_log=False))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30 * SCALE
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
        time.sleep(0.05)
    try:
        schema = schemathesis.openapi.from_url(f"http://127.0.0.1:{port}/openapi.json")
        operations = [result.ok() for result in schema.get_all_operations()]
        assert operations
        for operation, mode in itertools.product(operations, schemathesis.GenerationMode):
            @given(case=operation.as_strategy(generation_mode=mode))
            @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            def call(case) -> None:
                case.call_and_validate(checks=[not_a_server_error],
                                       timeout=30 * SCALE)

            try:
                call()
            except Unsatisfiable:  # no parameters or body to make invalid
                assert mode is schemathesis.GenerationMode.NEGATIVE, operation.label
    finally:
        server.should_exit = True
        thread.join(timeout=10 * SCALE)
