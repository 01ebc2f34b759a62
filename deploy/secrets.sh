#!/usr/bin/env bash
# Secrets of the compose stack: `make secrets` (or deploy/secrets.sh [DIR]).
# Writes a random control token, Zenoh password and Grafana admin password into DIR
# (default deploy/secrets, or AOI3D_SECRETS_DIR); an existing file is kept, so running it
# again changes nothing. The folder is 0700 (only you read it on the host); the files are
# 0644 because compose without swarm bind-mounts them unchanged into containers whose users
# (aoi3d, nobody, grafana) do not own them.
set -euo pipefail
dir=${1:-${AOI3D_SECRETS_DIR:-$(dirname "$0")/secrets}}
mkdir -p "$dir"
chmod 0700 "$dir"
for name in control_token zenoh_password grafana_admin_password; do
    [ -s "$dir/$name" ] && continue
    python3 -c 'import secrets, sys; sys.stdout.write(secrets.token_urlsafe(32))' >"$dir/$name.tmp"
    chmod 0644 "$dir/$name.tmp"
    mv "$dir/$name.tmp" "$dir/$name"
    echo "secrets: wrote $dir/$name" >&2
done
