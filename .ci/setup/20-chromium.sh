#!/usr/bin/env bash
# Debian's Chromium for the console's browser test (tests/browser/), driven by Playwright for
# Python with executable_path=/usr/bin/chromium: Playwright's own browser download cannot work
# on these machines.
set -euo pipefail
source "$(dirname "$0")/../lib.sh"
need_apt chromium chromium
