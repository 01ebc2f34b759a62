#!/usr/bin/env bash
# A Debian bookworm base image made with debootstrap, for engines that cannot pull
# python:3.11-slim-bookworm from a registry (the development machines of this project).
#
#   deploy/base-image.sh            prints the image reference, e.g. aoi3d-base:bookworm-3f2c...
#   docker build --build-arg BASE_IMAGE=$(deploy/base-image.sh) -f deploy/Dockerfile .
#
# bookworm's python3 is 3.11, as requires-python asks; python3-venv gives the image's venv its
# pip; gcc and libc6-dev build the fused kernels of aoi3d/field/native.py in the image's build
# stage (the build runs with no network, so the compiler must be in the base). The tag is a hash of this script, so an unchanged script finds its image in the engine
# (seconds); a rootfs tarball cached in AOI3D_BASE_CACHE (default ~/.cache/aoi3d/base) is
# imported without debootstrap after the engine's images are gone. Needs root, debootstrap
# (installed with apt if missing) and a Debian mirror (AOI3D_DEBIAN_MIRROR).
set -euo pipefail

SUITE=bookworm
MIRROR=${AOI3D_DEBIAN_MIRROR:-http://deb.debian.org/debian}
PACKAGES=python3,python3-venv,ca-certificates,gcc,libc6-dev
CACHE=${AOI3D_BASE_CACHE:-$HOME/.cache/aoi3d/base}
HASH=$( (cat "$0"; echo "$SUITE $PACKAGES") | sha256sum | cut -c1-12)
TAG=aoi3d-base:$SUITE-$HASH
TARBALL=$CACHE/$SUITE-$HASH.tar

say() { echo "base-image: $*" >&2; }

if docker image inspect "$TAG" >/dev/null 2>&1; then
    say "$TAG is in the engine"
    echo "$TAG"; exit 0
fi

if [ ! -s "$TARBALL" ]; then
    if ! command -v debootstrap >/dev/null 2>&1; then
        say "installing debootstrap (apt)"
        apt-get update -q >&2
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
            debootstrap >&2
    fi
    mkdir -p "$CACHE"
    root=$(mktemp -d "$CACHE/rootfs.XXXXXX")
    trap 'rm -rf "$root"' EXIT
    say "debootstrap $SUITE ($PACKAGES) from $MIRROR (a few minutes)"
    debootstrap --variant=minbase --include="$PACKAGES" "$SUITE" "$root" "$MIRROR" >&2
    # what a container never needs: package caches and lists, docs, the build host's name
    rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* \
        "$root"/usr/share/doc/* "$root"/usr/share/man/* "$root"/usr/share/info/* \
        "$root"/var/log/*.log "$root"/etc/hostname
    cat >"$root/etc/apt/sources.list" <<SOURCES
deb $MIRROR $SUITE main
deb $MIRROR $SUITE-updates main
deb http://deb.debian.org/debian-security $SUITE-security main
SOURCES
    tar --numeric-owner -C "$root" -cf "$TARBALL.tmp" .
    mv "$TARBALL.tmp" "$TARBALL"
fi

say "importing $TARBALL as $TAG"
docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["bash"]' \
    "$TARBALL" "$TAG" >/dev/null
echo "$TAG"
