#!/usr/bin/env bash
# Build the lrfslam image with podman, the way this host reaches the package index:
# its CA bundle is mounted into the build (needed where TLS to the index is intercepted or
# re-signed) and its pip index settings are passed as build arguments. Nothing host-specific
# ends up in the image or the repository. Docker users do not need this: `docker compose up --build`.
#
#   deploy/podman-build.sh [extra podman build args]      (from anywhere in the checkout)
#
# Env: LRFSLAM_IMAGE (default lrfslam:latest, the name deploy/compose.yaml uses).
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
image=${LRFSLAM_IMAGE:-lrfslam:latest}
args=(build -f "$root/deploy/Dockerfile" -t "$image")

# /etc/ssl/certs holds the bundle PIP_CERT and /etc/pip.conf point at on Debian-like hosts.
[[ -d /etc/ssl/certs ]] && args+=(-v /etc/ssl/certs:/etc/ssl/certs:ro)
[[ -r /etc/pip.conf ]] && args+=(-v /etc/pip.conf:/etc/pip.conf:ro)
for var in PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_TRUSTED_HOST PIP_CERT; do
    value=${!var:-}
    # file:// indexes are host folders the build cannot see; pip would only warn about them.
    value=$(tr ' ' '\n' <<<"$value" | grep -v '^file:' | paste -sd' ' || true)
    [[ -n $value ]] && args+=(--build-arg "$var=$value")
done

exec podman "${args[@]}" "$@" "$root"
