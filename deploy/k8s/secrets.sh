#!/usr/bin/env bash
# The Kubernetes Secrets of deploy/k8s, from the files `make secrets` writes (deploy/secrets.sh:
# the control token, the Zenoh password, the Zenoh TLS CA and the certificates of the routers
# "router" and "router-edge" and of the clients). Prints the manifests; nothing is written:
#
#   make secrets && deploy/k8s/secrets.sh | kubectl apply -f -
#   deploy/k8s/secrets.sh [DIR] [NAMESPACE]     (defaults: deploy/secrets, aoi3d)
#
# Four Secrets, so that each pod mounts only what compose gives its service: aoi3d-control
# (the control token), aoi3d-zenoh (password and CA: every Zenoh process), aoi3d-zenoh-client
# (the services' and workers' certificate), aoi3d-zenoh-router and aoi3d-zenoh-router-edge
# (each router's). The CA's key (zenoh_tls_ca_key) never leaves DIR. `kubectl create ...
# --dry-run=client` makes the manifests: no cluster is contacted.
set -euo pipefail
dir=${1:-${AOI3D_SECRETS_DIR:-$(dirname "$0")/../secrets}}
namespace=${2:-aoi3d}
kubectl=${KUBECTL:-kubectl}

secret() {
    local name=$1; shift
    local args=() key
    for key in "$@"; do
        if ! [ -s "$dir/$key" ]; then
            echo "k8s secrets: $dir/$key is missing (run make secrets)" >&2
            exit 1
        fi
        args+=("--from-file=$key=$dir/$key")
    done
    echo "---"
    "$kubectl" create secret generic "$name" --namespace "$namespace" "${args[@]}" \
        --dry-run=client -o yaml | grep -v '^  creationTimestamp: null$'
}

secret aoi3d-control control_token
secret aoi3d-zenoh zenoh_password zenoh_tls_ca
secret aoi3d-zenoh-client zenoh_tls_client_cert zenoh_tls_client_key
secret aoi3d-zenoh-router zenoh_tls_router_cert zenoh_tls_router_key
secret aoi3d-zenoh-router-edge zenoh_tls_router-edge_cert zenoh_tls_router-edge_key
