# sekd in a container: CPU torch by default, runs as a non-root user.
#
#   docker build -t sekd .                                   # CPU image (python:3.11-slim base)
#   docker build -t sekd --build-arg UID=$(id -u) .          # files written to mounts belong to you
#   docker build -t sekd:cuda --build-arg TORCH_VARIANT=cu128 .   # CUDA build of torch (several GB)
#   docker run --rm -v "$PWD/photos:/data/photos:ro" -v "$PWD/out:/data/out" sekd \
#       reconstruct /data/photos -o /data/out/model
#
# Peer weights (DISK, ALIKED, XFeat) and the benchmark data are read from $SEKD_SHARED=/shared:
# mount the project's shared folder there (-v /path/to/shared:/shared:ro), or only its
# weights (-v /path/to/weights:/shared/weights:ro). See docs/docker.md.
#
# Build arguments:
#   BASE_IMAGE      any Debian/Ubuntu-like image with python3 >= 3.10 and its venv module
#                   (default python:3.11-slim; docker/build_base.sh makes one from Debian
#                   packages when no image registry is reachable)
#   TORCH_VERSION   2.13.0, the release the project is tested with
#   TORCH_VARIANT   cpu (default: the ~190 MB CPU build from PyTorch's wheel index), a CUDA tag
#                   such as cu128, or "pypi" for PyPI's default torch wheel (on x86_64 Linux that
#                   is the CUDA build, several GB)
#   TORCH_INDEX_URL where the variant's wheels are (default PyTorch's index for TORCH_VARIANT)
#   UID, GID        the numeric user and group the image runs as (default 1000); `docker run
#                   --user` overrides them at run time too
#
# docker/local/ (not committed) is bind-mounted during the build: wheels there are used
# before any index (e.g. a torch-2.13.0+cpu wheel when PyTorch's index cannot be reached),
# and docker/local/ca-bundle.crt, when present, is the CA bundle pip trusts (networks that
# intercept TLS). Neither ends up in the image.
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ARG TORCH_VERSION=2.13.0
ARG TORCH_VARIANT=cpu
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/${TORCH_VARIANT}
ARG UID=1000
ARG GID=1000

ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONUNBUFFERED=1 \
    VIRTUAL_ENV=/opt/venv PATH=/opt/venv/bin:$PATH \
    SEKD_SHARED=/shared MPLCONFIGDIR=/tmp/matplotlib

# OpenMP (torch, OpenCV) and GLib (OpenCV); a base that already has them skips apt.
RUN if ! dpkg -s libgomp1 libglib2.0-0 >/dev/null 2>&1; then \
        apt-get update && apt-get install -y --no-install-recommends libgomp1 libglib2.0-0 \
        && rm -rf /var/lib/apt/lists/*; \
    fi \
 && python3 -m venv /opt/venv

# torch first, pinned, so the project's "torch>=2.2" is already satisfied and pip never
# pulls PyPI's default (CUDA) wheel for a CPU image.
RUN --mount=type=bind,source=docker/local,target=/tmp/local \
    set -e; \
    if [ -f /tmp/local/ca-bundle.crt ]; then export PIP_CERT=/tmp/local/ca-bundle.crt; fi; \
    if [ "$TORCH_VARIANT" = pypi ]; then spec="torch==${TORCH_VERSION}"; index=""; \
    else spec="torch==${TORCH_VERSION}+${TORCH_VARIANT}"; index="--extra-index-url ${TORCH_INDEX_URL}"; fi; \
    if ls /tmp/local/torch-${TORCH_VERSION}+${TORCH_VARIANT}-*.whl >/dev/null 2>&1; then index=""; fi; \
    pip install --find-links /tmp/local $index "$spec"

WORKDIR /opt/sekd
COPY pyproject.toml README.md ./
COPY sekd_sfm ./sekd_sfm
RUN --mount=type=bind,source=docker/local,target=/tmp/local \
    if [ -f /tmp/local/ca-bundle.crt ]; then export PIP_CERT=/tmp/local/ca-bundle.crt; fi; \
    pip install --find-links /tmp/local . && rm -rf build *.egg-info

# A non-root user; /data is the working folder for mounted photos and outputs.
RUN groupadd --gid ${GID} sekd \
 && useradd --uid ${UID} --gid ${GID} --create-home --shell /bin/bash sekd \
 && mkdir -p /data /shared \
 && chown sekd:sekd /data
USER sekd
WORKDIR /data
RUN sekd doctor

ENTRYPOINT ["sekd"]
CMD ["--help"]
