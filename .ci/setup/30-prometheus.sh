#!/usr/bin/env bash
# Prometheus and promtool (Debian's prometheus package) for the alert-rule unit tests and the
# real-Prometheus integration test. Debian's package starts no daemon without systemd; stop it
# where one runs, the tests start their own.
set -euo pipefail
source "$(dirname "$0")/../lib.sh"
need_apt promtool prometheus
if command -v systemctl >/dev/null 2>&1; then
    systemctl disable --now prometheus >/dev/null 2>&1 || true
fi
