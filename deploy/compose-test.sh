#!/usr/bin/env bash
# `make compose-test`: the compose stack built and run end to end (tests/containers/).
#   1. an engine: the running one, else a private dockerd (deploy/engine.sh; stopped again at
#      the end when this script started it)
#   2. the images, without a registry (deploy/build-images.sh)
#   3. pytest tests/containers: up --wait, Quality, PUT /policy, Prometheus targets, a killed
#      dispatcher restarted, down -v leaves nothing
# Waits scale with AOI3D_TEST_TIMEOUT_SCALE. Prints how long each phase took.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
start=$(date +%s)
started_engine=0
if ! deploy/engine.sh env >/dev/null 2>&1; then started_engine=1; fi
env_lines=$(deploy/engine.sh start)
eval "$env_lines"
cleanup() {
    if [ "$started_engine" = 1 ]; then deploy/engine.sh stop || true; fi
}
trap cleanup EXIT
export AOI3D_PROMETHEUS_IMAGE=${AOI3D_PROMETHEUS_IMAGE:-aoi3d-prometheus:debian}
t=$(date +%s)
deploy/build-images.sh
echo "compose-test: images built in $(( $(date +%s) - t ))s" >&2
AOI3D_COMPOSE_TEST=1 "$PY" -m pytest -p no:cacheprovider -v -s -m containers tests/containers "$@"
echo "compose-test: passed in $(( $(date +%s) - start ))s (engine, images, stack)" >&2
