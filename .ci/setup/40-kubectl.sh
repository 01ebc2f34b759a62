#!/usr/bin/env bash
# kubectl with its built-in kustomize, for tests/deploy/test_k8s.py (deploy/k8s rendered and
# validated offline). The CI machine image carries kubectl 1.32 (kustomize 5.5); Debian's
# kubernetes-client (1.20) is too old to render the overlays (kustomize's `labels` and
# `replicas`). No kubectl, or one whose kustomize cannot render them, fails the run here,
# rather than letting the tests skip.
set -euo pipefail
cd "$(dirname "$0")/../.."
if ! command -v kubectl >/dev/null 2>&1; then
    echo "kubectl is not installed: deploy/k8s cannot be rendered (the machine image has it)" >&2
    exit 1
fi
kubectl version --client 2>/dev/null | sed 's/^/    /'
for overlay in deploy/k8s/overlays/*/; do
    kubectl kustomize "$overlay" >/dev/null
done
echo "    kustomize renders every overlay of deploy/k8s"
