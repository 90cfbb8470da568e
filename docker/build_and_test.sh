#!/usr/bin/env bash
# Build the sekd image and run it: `sekd doctor`, then the README's quick start (extract,
# pairs, match, reconstruct, export) on fountain-P11 at 640 px, as a non-root user, with the
# shared data mounted read-only. Prints every command and its output.
#
#   docker/build_and_test.sh                         # podman, base built from Debian packages
#   ENGINE=docker BASE_IMAGE=python:3.11-slim docker/build_and_test.sh
#
# Environment: ENGINE (podman), BASE_IMAGE (localhost/debian-bookworm-base, made by
# build_base.sh when missing), IMAGE (localhost/sekd:cpu), SHARED (../shared beside the
# checkout, or $SEKD_SHARED), OUT (a new temporary folder), RUN_UID (1000), SCENE (fountain-P11),
# TORCH_WHEEL (a local torch wheel to build with instead of PyTorch's index), PIP_CERT.
set -euo pipefail

HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(dirname "$HERE")
ENGINE=${ENGINE:-podman}
IMAGE=${IMAGE:-localhost/sekd:cpu}
BASE_IMAGE=${BASE_IMAGE:-localhost/debian-bookworm-base}
SHARED=$(cd "${SHARED:-${SEKD_SHARED:-$ROOT/../shared}}" && pwd)
RUN_UID=${RUN_UID:-1000}
SCENE=${SCENE:-fountain-P11}
TORCH_VERSION=${TORCH_VERSION:-2.13.0}

if [ "$ENGINE" = podman ]; then
    # Sandboxed hosts refuse crun and the default ulimits; see containers.conf.
    export CONTAINERS_CONF=${CONTAINERS_CONF:-$HERE/containers.conf}
    RUNTIME=${RUNTIME:-$(command -v runc || true)}
    ENGINE="podman${RUNTIME:+ --runtime $RUNTIME}"
fi
say() { printf '\n$ %s\n' "$*"; }
run() { say "$*"; "$@"; }

# 1. Base image (cached): only the Debian-packages base is built here.
if [ "$BASE_IMAGE" = localhost/debian-bookworm-base ]; then
    PODMAN="$ENGINE" "$HERE/build_base.sh"
fi

# 2. Build-time files from this host (docker/local/, never in the image): the CA bundle the
# host's pip trusts (networks that intercept TLS), and CPU torch from PyTorch's CPU index
# when reachable, else a local wheel.
LOCAL=$HERE/local
CERT=${PIP_CERT:-$(pip config get global.cert 2>/dev/null || true)}
if [ -n "$CERT" ] && [ -f "$CERT" ]; then cp "$CERT" "$LOCAL/ca-bundle.crt"; fi
if [ -n "${TORCH_WHEEL:-}" ]; then
    cp -n "$TORCH_WHEEL" "$LOCAL/"
elif ! ls "$LOCAL"/torch-"$TORCH_VERSION"+cpu-*.whl >/dev/null 2>&1 \
     && ! curl -fsS -o /dev/null --max-time 10 https://download.pytorch.org/whl/cpu/torch/ 2>/dev/null; then
    echo "PyTorch's CPU index is unreachable: fetching torch==$TORCH_VERSION+cpu with this host's pip into docker/local/"
    pip download --no-deps --only-binary=:all: --python-version 3.11 --platform manylinux_2_28_x86_64 \
        -d "$LOCAL" "torch==$TORCH_VERSION+cpu"
fi

# 3. The image. --network host: the build needs PyPI only, and some hosts cannot set up
# the engine's own network namespace.
start=$(date +%s)
run $ENGINE build --network host -t "$IMAGE" \
    --build-arg BASE_IMAGE="$BASE_IMAGE" --build-arg UID="$RUN_UID" --build-arg GID="$RUN_UID" "$ROOT"
echo "build: $(( $(date +%s) - start )) s"
$ENGINE image ls "$IMAGE"

# 4. Run it: doctor, then the quick start into a folder owned by the run user.
OUT=${OUT:-$(mktemp -d "${TMPDIR:-/tmp}/sekd-docker-out.XXXXXX")}
mkdir -p "$OUT"
[ "$(id -u)" = 0 ] && chown "$RUN_UID:$RUN_UID" "$OUT"
IMAGES=/shared/data/sfm/$SCENE/images
sekd() {
    say "sekd $*"
    $ENGINE run --rm --network none --user "$RUN_UID:$RUN_UID" \
        -v "$SHARED:/shared:ro" -v "$OUT:/data/out" "$IMAGE" "$@"
}
say "id inside the container"; $ENGINE run --rm --entrypoint id "$IMAGE"
sekd doctor
sekd extract "$IMAGES" -o out/features.h5 --resize-max 640 --no-progress
sekd pairs out/features.h5 -o out/pairs.txt
sekd match out/features.h5 out/pairs.txt -o out/matches.h5 --no-progress
sekd reconstruct "$IMAGES" -o out --resize-max 640 --no-progress
sekd export out/model -o out/points.ply --format ply
say "ls -ln $OUT (files belong to uid $RUN_UID)"; ls -ln "$OUT"
echo "quick start in the container: OK"
