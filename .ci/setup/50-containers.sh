#!/usr/bin/env bash
# make compose-test (run by .ci/run after make test): Debian's Docker engine (docker.io) and
# debootstrap (the base image, as no registry answers). deploy/engine.sh and
# deploy/base-image.sh would install them too; here CI installs them up front. A failure is
# not fatal: .ci/run then prints why compose-test is skipped.
source "$(dirname "$0")/../lib.sh"
need_apt dockerd docker.io || echo "docker.io could not be installed: compose-test will be skipped"
need_apt debootstrap debootstrap || echo "debootstrap could not be installed"
exit 0
