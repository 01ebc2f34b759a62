#!/usr/bin/env bash
# Secrets of the compose stack: `make secrets` (or deploy/secrets.sh [DIR]).
# Writes a random control token, Zenoh password and Grafana admin password into DIR
# (default deploy/secrets, or AOI3D_SECRETS_DIR); an existing file is kept, so running it
# again changes nothing. The folder is 0700 (only you read it on the host); the files are
# 0644 because compose without swarm bind-mounts them unchanged into containers whose users
# (aoi3d, nobody, grafana) do not own them.
#
# Zenoh TLS (openssl): a private CA (zenoh_tls_ca, its key zenoh_tls_ca_key, which no
# container gets) and, per router name in AOI3D_ZENOH_ROUTERS (default "router,router-edge,
# router-a,router-b": the routers' DNS names in compose.yaml and compose.multihost.yaml), a
# certificate zenoh_tls_<name>_cert with its key
# zenoh_tls_<name>_key, signed by the CA, valid for DNS:<name>, DNS:localhost, IP:127.0.0.1,
# IP:::1 and any names in AOI3D_ZENOH_TLS_SANS (e.g. "DNS:host-a,IP:10.0.0.5" for routers
# reached across hosts). For compose's default router: zenoh_tls_router_cert and
# zenoh_tls_router_key. Also a client certificate for mutual TLS (zenoh_tls_client_cert,
# zenoh_tls_client_key). Kept if present too; a certificate the CA in DIR did not sign is made again. To
# change the names of an existing certificate, delete it and run this again.
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

# ----------------------------------------------------------------------------- Zenoh TLS
ca="$dir/zenoh_tls_ca"
ca_key="$dir/zenoh_tls_ca_key"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
if ! [ -s "$ca" ] || ! [ -s "$ca_key" ]; then
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$tmp/ca_key" 2>/dev/null
    openssl req -x509 -new -key "$tmp/ca_key" -sha256 -days 3650 -subj "/CN=aoi3d Zenoh CA" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -addext "subjectKeyIdentifier=hash" -out "$tmp/ca"
    chmod 0600 "$tmp/ca_key"  # the CA's key stays on the host: no container gets it
    chmod 0644 "$tmp/ca"
    mv "$tmp/ca_key" "$ca_key"
    mv "$tmp/ca" "$ca"
    echo "secrets: wrote $ca (Zenoh TLS CA) and its key" >&2
fi

# leaf NAME USAGE SANS: zenoh_tls_NAME_cert and _key, signed by the CA (kept when valid).
leaf() {
    local name=$1 usage=$2 sans=$3
    local cert="$dir/zenoh_tls_${name}_cert" key="$dir/zenoh_tls_${name}_key"
    if [ -s "$cert" ] && [ -s "$key" ] && openssl verify -CAfile "$ca" "$cert" >/dev/null 2>&1
    then
        return
    fi
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$tmp/key" 2>/dev/null
    openssl req -new -key "$tmp/key" -subj "/CN=$name" -out "$tmp/csr"
    {
        echo "basicConstraints=critical,CA:FALSE"
        echo "keyUsage=critical,digitalSignature"
        echo "extendedKeyUsage=$usage"
        echo "subjectAltName=$sans"
    } >"$tmp/ext"
    openssl x509 -req -in "$tmp/csr" -CA "$ca" -CAkey "$ca_key" -CAcreateserial \
        -CAserial "$tmp/serial" -sha256 -days 825 -extfile "$tmp/ext" -out "$tmp/cert" 2>/dev/null
    chmod 0644 "$tmp/key" "$tmp/cert"
    mv "$tmp/key" "$key"
    mv "$tmp/cert" "$cert"
    echo "secrets: wrote $cert and its key" >&2
}

routers=${AOI3D_ZENOH_ROUTERS:-router,router-edge,router-a,router-b}
for router in ${routers//,/ }; do
    case $router in
        client|ca|ca_key) echo "secrets: '$router' cannot be a router name" >&2; exit 2 ;;
        *[!A-Za-z0-9.-]*) echo "secrets: bad router name '$router'" >&2; exit 2 ;;
    esac
    leaf "$router" serverAuth,clientAuth \
        "DNS:$router,DNS:localhost,IP:127.0.0.1,IP:::1${AOI3D_ZENOH_TLS_SANS:+,$AOI3D_ZENOH_TLS_SANS}"
done
leaf client clientAuth "DNS:aoi3d-client"
