#!/usr/bin/env bash
# deploy/zenoh/make-certs.sh OUT_DIR ROBOT_HOST [MORE_NAMES_OR_IPS...]: `lrfslam certs` (src/lrfslam/tools/certs.py) under its old name and arguments; needs lrfslam installed.
set -euo pipefail; (($# >= 2)) || { sed -n 2p "$0" >&2; exit 2; }; out=$1; shift; exec lrfslam certs "$out" "${@/#/--host=}"
