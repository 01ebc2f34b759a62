# Sourced by .ci/setup/*.sh: install Debian packages a test needs, once per CI run.
# need_apt CMD PKG...   installs PKG... with apt-get when CMD is not on PATH.
need_apt() {
    local cmd=$1; shift
    command -v "$cmd" >/dev/null 2>&1 && return 0
    local sudo=""
    [ "$(id -u)" = 0 ] || sudo="sudo -n"
    if [ ! -e /tmp/.aoi3d-apt-updated ]; then
        $sudo apt-get update -q && touch /tmp/.aoi3d-apt-updated
    fi
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q --no-install-recommends "$@"
}
