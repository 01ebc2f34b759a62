"""Every REST operation of the five services, the recorder and the ingest fuzzed from its own
OpenAPI (schemathesis, over HTTP against the real apps served by uvicorn on 127.0.0.1, with a
MemoryBus): no input, valid (positive) or not (negative cases), gets a 5xx (issues 11 and
44). The number of examples per operation is bounded (AOI3D_FUZZ_EXAMPLES, 15 by default) to
keep the suite quick; `make fuzz` raises it."""

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
from tests.support.guard import FUZZED, build
from tests.support.timeouts import timeout_scale

EXAMPLES = int(os.environ.get("AOI3D_FUZZ_EXAMPLES", "15"))
SCALE = timeout_scale()


def no_server_error(ctx, response, case) -> bool | None:
    """Schemathesis's check, but for a /readyz that says 503: not ready is its answer (the
    ingest without frames from its cameras), not a failure."""
    if case.operation.path == "/readyz" and response.status_code == 503:
        return None
    return not_a_server_error(ctx, response, case)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("service", FUZZED)
def test_no_operation_answers_a_server_error(service: str, dataset: SceneDataset,
                                             tmp_path) -> None:
    app = build(service, dataset, files_roots=[str(tmp_path)])
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
                case.call_and_validate(checks=[no_server_error],
                                       timeout=30 * SCALE)

            try:
                call()
            except Unsatisfiable:  # no parameters or body to make invalid
                assert mode is schemathesis.GenerationMode.NEGATIVE, operation.label
    finally:
        server.should_exit = True
        thread.join(timeout=10 * SCALE)
