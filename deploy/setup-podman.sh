#!/usr/bin/env bash
# Make a Debian bookworm machine (CI, a developer box without a Docker engine) able to run
# deploy/compose.yaml with podman. Run as root; safe to run again: every step checks first.
#
#   sudo deploy/setup-podman.sh
#
# Why each step exists (see deploy/README.md):
#  * podman + runc: Debian's crun fails on hybrid-cgroup hosts ("cgroups in hybrid mode not supported").
#  * default_ulimits = []: sandboxed hosts refuse setrlimit(NOFILE/NPROC) for containers.
#  * a local base image: where no image registry is reachable, `FROM python:3.11-slim-bookworm`
#    cannot be pulled, so a minimal bookworm with Python 3.11 is built with debootstrap and given
#    that name. Users with a registry never need it: they pull the real image.
#  * iproute2: `ip netns`, for the hosts-as-namespaces test (tests/deploy/test_netns_hosts.py).
#  * podman-compose from PyPI: Debian's 1.0.3 predates `depends_on: condition: service_healthy`.
set -euo pipefail

BASE_IMAGE=${LRFSLAM_BASE_IMAGE:-docker.io/library/python:3.11-slim-bookworm}
PODMAN_COMPOSE_VERSION=${LRFSLAM_PODMAN_COMPOSE_VERSION:-1.6.0}
PODMAN_COMPOSE_VENV=/opt/podman-compose

log() { printf '[setup-podman %(%H:%M:%S)T] %s\n' -1 "$*"; }

if [[ $(id -u) -ne 0 ]]; then
    echo "setup-podman.sh: run as root (it installs packages and writes /etc/containers)" >&2
    exit 1
fi

# ---- packages -------------------------------------------------------------------------------
missing=()
for pkg in podman runc debootstrap python3-venv iproute2; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
    log "installing ${missing[*]}"
    apt-get update -q
    # With recommends: they bring catatonit (for `init: true`) and the network helpers.
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${missing[@]}"
else
    log "packages already installed"
fi

# ---- containers.conf ------------------------------------------------------------------------
# A drop-in, so an administrator's own containers.conf stays untouched and a rerun rewrites
# only our file.
mkdir -p /etc/containers/containers.conf.d
conf=/etc/containers/containers.conf.d/50-lrfslam.conf
cat >"$conf.tmp" <<'EOF'
# Written by lrfslam deploy/setup-podman.sh.
[containers]
# Sandboxed hosts refuse to raise RLIMIT_NOFILE/NPROC; keep the engine's limits.
default_ulimits = []

[engine]
# crun from Debian fails on hybrid cgroup hosts; runc works.
runtime = "runc"
EOF
if cmp -s "$conf.tmp" "$conf"; then rm "$conf.tmp"; else mv "$conf.tmp" "$conf"; log "wrote $conf"; fi

runtime=$(podman info --format '{{.Host.OCIRuntime.Name}}')
if [[ $runtime != runc ]]; then
    echo "setup-podman.sh: podman still uses '$runtime' after writing $conf" >&2
    exit 1
fi

# ---- base image -----------------------------------------------------------------------------
debian_mirror() {
    # The first "bookworm" (not -security/-updates) archive of this machine's apt sources, both
    # the deb822 (*.sources) and the one-line (*.list) formats.
    local f
    for f in /etc/apt/sources.list.d/*.sources; do
        [[ -r $f ]] || continue
        awk 'BEGIN{RS=""; FS="\n"}
             { uri=""; deb=0; suite=0
               for (i = 1; i <= NF; i++) {
                 if ($i ~ /^Types:.*(^|[ \t])deb([ \t]|$)/) deb=1
                 if ($i ~ /^URIs:/) { split($i, a, /[ \t]+/); uri=a[2] }
                 if ($i ~ /^Suites:/ && $i ~ /[ \t]bookworm([ \t]|$)/) suite=1
               }
               if (deb && suite && uri != "") { print uri; exit } }' "$f"
    done
    { cat /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null || true; } |
        awk '$1 == "deb" { i = 2; if ($2 ~ /^\[/) { while ($i !~ /\]$/) i++; i++ }
                           if ($(i+1) == "bookworm") print $i }'
}

if podman image exists "$BASE_IMAGE"; then
    log "base image $BASE_IMAGE already present"
else
    mirror=${LRFSLAM_DEBIAN_MIRROR:-$(debian_mirror | head -n1)}
    if [[ -z $mirror ]]; then
        echo "setup-podman.sh: no bookworm archive in /etc/apt/sources*; set LRFSLAM_DEBIAN_MIRROR" >&2
        exit 1
    fi
    rootfs=$(mktemp -d /var/tmp/lrfslam-rootfs.XXXXXX)
    trap 'rm -rf "$rootfs"' EXIT
    log "debootstrap bookworm from $mirror (takes 2-3 minutes)"
    debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates \
        bookworm "$rootfs" "$mirror" >/var/tmp/lrfslam-debootstrap.log 2>&1 ||
        { tail -n 20 /var/tmp/lrfslam-debootstrap.log >&2; exit 1; }
    # The official image has `python` and `pip`; give the stand-in the same names so commands
    # written against python:3.11-slim-bookworm behave the same on both.
    ln -sf /usr/bin/python3 "$rootfs/usr/local/bin/python"
    ln -sf /usr/bin/pip3 "$rootfs/usr/local/bin/pip"
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    log "importing the root file system as $BASE_IMAGE"
    tar -C "$rootfs" -c . | podman import -q --change 'CMD ["python3"]' \
        --message "bookworm minbase + python3 (lrfslam setup-podman.sh stand-in)" - "$BASE_IMAGE" >/dev/null
    rm -rf "$rootfs"
    trap - EXIT
fi

# ---- podman-compose -------------------------------------------------------------------------
# Its own venv: Debian's python refuses system-wide pip installs (PEP 668), and the project venv
# may not exist yet when this runs.
if [[ -x $PODMAN_COMPOSE_VENV/bin/podman-compose ]] &&
    [[ $("$PODMAN_COMPOSE_VENV/bin/pip" show podman-compose 2>/dev/null | awk '/^Version:/{print $2}') == "$PODMAN_COMPOSE_VERSION" ]]; then
    log "podman-compose $PODMAN_COMPOSE_VERSION already installed"
else
    log "installing podman-compose $PODMAN_COMPOSE_VERSION"
    /usr/bin/python3 -m venv "$PODMAN_COMPOSE_VENV"
    "$PODMAN_COMPOSE_VENV/bin/pip" install -q "podman-compose==$PODMAN_COMPOSE_VERSION"
fi
ln -sf "$PODMAN_COMPOSE_VENV/bin/podman-compose" /usr/local/bin/podman-compose

log "ready: $(podman --version), runtime $runtime, $(podman-compose --version 2>/dev/null | head -n1)"
