#!/usr/bin/env bash
# Node and the JavaScript MCAP reader Foxglove and Lichtblick are built on (@mcap/core, with
# protobufjs for the schemas), for tests/foxglove/: a recording must open with their reader, not
# only with Python's. Packages from the npm registry, versions pinned in tests/foxglove/package.json.
set -euo pipefail
source "$(dirname "$0")/../lib.sh"
need_apt node nodejs
need_apt npm npm
cd "$(dirname "$0")/../../tests/foxglove"
npm install --no-audit --no-fund --ignore-scripts --loglevel=error
