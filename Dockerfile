# CPU image of sekd: `docker build -t sekd .`
# Run on a folder of photos mounted at /data:
#   docker run --rm -v "$PWD/photos:/data/photos" -v "$PWD/out:/data/out" sekd \
#       extract /data/photos -o /data/out/features.h5      (the embedded model; --weights for another)
# To get the small CPU-only torch build instead of PyPI's default, pass the CPU wheel index
# of PyTorch with --build-arg PIP_TORCH_ARGS="--index-url <cpu wheel index>".
FROM python:3.11-slim

ARG TORCH_SPEC="torch==2.13.0"
ARG PIP_TORCH_ARGS=""
ENV PIP_NO_CACHE_DIR=1 PYTHONUNBUFFERED=1

RUN apt-get update \
 && apt-get install -y --no-install-recommends libglib2.0-0 libgomp1 \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/sekd
RUN pip install ${PIP_TORCH_ARGS} "${TORCH_SPEC}"
COPY pyproject.toml README.md ./
COPY sekd_sfm ./sekd_sfm
COPY cli ./cli
RUN pip install . && sekd doctor

WORKDIR /data
ENTRYPOINT ["sekd"]
CMD ["--help"]
