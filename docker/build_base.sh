#!/usr/bin/env bash
# Build a minimal Debian bookworm base image with Python 3.11 from Debian's packages
# (debootstrap), for hosts that cannot pull python:3.11-slim from an image registry.
# The result, localhost/debian-bookworm-base, is what build_and_test.sh passes to the
# Dockerfile as BASE_IMAGE. Cached: does nothing if the image already exists
# (FORCE=1 rebuilds it). Needs root, debootstrap and podman.
#
#   sudo docker/build_base.sh                      # mirror from /etc/apt, else deb.debian.org
#   MIRROR=http://ftp.de.debian.org/debian sudo docker/build_base.sh
set -euo pipefail

BASE_TAG=${BASE_TAG:-localhost/debian-bookworm-base}
SUITE=${SUITE:-bookworm}
HERE=$(cd "$(dirname "$0")" && pwd)
export CONTAINERS_CONF=${CONTAINERS_CONF:-$HERE/containers.conf}
PODMAN=${PODMAN:-"podman --runtime /usr/sbin/runc"}

if [ "${FORCE:-0}" != 1 ] && $PODMAN image exists "$BASE_TAG"; then
    echo "base image $BASE_TAG exists (FORCE=1 to rebuild)"
    exit 0
fi

# The Debian mirror apt already uses on this host, so the base comes from the same place.
if [ -z "${MIRROR:-}" ]; then
    MIRROR=$(grep -hoE '^URIs: *http[^ ]*/debian$' /etc/apt/sources.list.d/*.sources 2>/dev/null \
             | head -1 | sed 's/^URIs: *//')
    MIRROR=${MIRROR:-http://deb.debian.org/debian}
fi

WORK=$(mktemp -d "${TMPDIR:-/tmp}/sekd-base.XXXXXX")
trap 'rm -rf "$WORK"' EXIT
ROOTFS=$WORK/rootfs

# minbase = essential + apt only; python3-venv gives ensurepip, so pip comes from the venv.
# libgomp1 (OpenMP for torch/OpenCV) and libglib2.0-0 are the runtime libraries sekd needs.
echo "debootstrap $SUITE from $MIRROR"
debootstrap --variant=minbase \
    --include=python3,python3-venv,python3-pip,ca-certificates,libgomp1,libglib2.0-0 \
    "$SUITE" "$ROOTFS" "$MIRROR"

# Same sources inside the image as on the host, and an empty apt cache (smaller image).
echo "deb $MIRROR $SUITE main" > "$ROOTFS/etc/apt/sources.list"
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/archives/*.deb

tar -C "$ROOTFS" -c . | $PODMAN import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["/bin/bash"]' \
    - "$BASE_TAG"
$PODMAN run --rm "$BASE_TAG" python3 --version
$PODMAN image ls "$BASE_TAG"
