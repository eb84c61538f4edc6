#!/usr/bin/env bash
# A private CA plus the certificates for deploy/zenoh/*.json5: the router's, one for the pipeline
# services (CN lrfslam-service) and one for monitors (CN lrfslam-monitor).
#
#   deploy/zenoh/make-certs.sh OUT_DIR ROBOT_HOST [MORE_NAMES_OR_IPS...]
#
# ROBOT_HOST is the name or address clients will dial (tls/<ROBOT_HOST>:7448); the router's
# certificate must carry it, or a client that verifies names refuses the connection. The common
# names are what router-tls-acl.json5 grants rights to: keep them in step. An existing CA in
# OUT_DIR is reused, so certificates issued earlier stay valid. Keep ca-key.pem off the robot.
set -euo pipefail

if (($# < 2)); then
    sed -n '2,10p' "$0" >&2
    exit 2
fi
out=$1
shift
mkdir -p "$out"
cd "$out"
umask 077

san="DNS:zenohd,DNS:localhost,IP:127.0.0.1"
for name in "$@"; do
    if [[ $name =~ ^[0-9.]+$ || $name == *:* ]]; then san+=",IP:$name"; else san+=",DNS:$name"; fi
done

if [[ ! -e ca.pem ]]; then
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 3650 \
        -subj "/CN=lrfslam CA" -keyout ca-key.pem -out ca.pem 2>/dev/null
fi

issue() {  # file name, common name, extensions
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$2" \
        -keyout "$1-key.pem" -out "$1.csr" 2>/dev/null
    printf '%b' "$3" >"$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days 825 \
        -extfile "$1.ext" -out "$1.pem" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
}
issue router lrfslam-router "subjectAltName=$san\nextendedKeyUsage=serverAuth,clientAuth\n"
issue service lrfslam-service "extendedKeyUsage=clientAuth\n"
issue monitor lrfslam-monitor "extendedKeyUsage=clientAuth\n"
chmod 644 ca.pem router.pem service.pem monitor.pem
echo "wrote $(pwd)/{ca,router,service,monitor}.pem and keys; router names: $san"
