# relightcli runtime image: ONNX Runtime + Embree on the CPU, no torch, no training code.
#   docker build -t relightcli .
#   docker run --rm -v "$PWD/in:/in" -v "$PWD/out:/out" relightcli /in --hdr /in/sky.hdr -o /out
# A maintainer's check against a real engine: docker/check.sh
#
# The base is pinned by digest: the multi-platform index of python:3.11-slim-bookworm (Python
# 3.11.16 on the Debian snapshot of 2026-08-24), copied from docker-library/repo-info,
# repos/python/remote/3.11-slim-bookworm.md at commit bc9bbb47. It was not pulled or checked
# against Docker Hub when it was pinned (no registry access there); the image was built and
# tested on a local stand-in instead: --build-arg BASE_IMAGE=local/python:3.11-slim-bookworm.
# To update: docker buildx imagetools inspect python:3.11-slim-bookworm (or docker pull it and
# read RepoDigests from docker image inspect), put the index digest below, rebuild, and run
# docker/check.sh.
ARG BASE_IMAGE=python:3.11-slim-bookworm@sha256:fe556eaffd0d96abd8685b83bb8a69addd0dc730fa193669a7df0d49ddcfac02

FROM ${BASE_IMAGE} AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md requirements.lock ./
COPY relightcli ./relightcli
# The models go into the wheel as package data (relightcli/models in site-packages)
COPY models ./models
# Bytecode compiled here, once (unchecked-hash: valid whatever the files' times, which the image
# never changes): the runtime writes none (PYTHONDONTWRITEBYTECODE), and without it every
# container compiled numpy, scipy, OpenCV's and our modules again, 1.1 s of each run's start
RUN python -m venv /opt/venv \
 && /opt/venv/bin/pip install --no-compile -c requirements.lock . \
 && /opt/venv/bin/python -m compileall -q -j 0 --invalidation-mode unchecked-hash /opt/venv/lib \
 && /opt/venv/bin/python -c "import importlib.util as u, sys; sys.exit(u.find_spec('torch') is not None)"

FROM ${BASE_IMAGE} AS runtime
# tini (Debian's; its layer adds 1.8 MB, the binary used is 28 KB) is PID 1: it handles
# signals from the first instruction, forwards them to relight and reaps. Every wheel we install
# loads only libc, libstdc++, libgcc and zlib from the system (tests/test_runtime_env.py checks
# this with ldd + dpkg).
RUN apt-get update \
 && apt-get install -y --no-install-recommends tini \
 && apt-get clean && rm -rf /var/lib/apt/lists/*
COPY --from=build /opt/venv /opt/venv
COPY docker/entrypoint.py /usr/local/lib/relight/entrypoint.py
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1
# relight info must find the installed models and write nothing to ~ (no ~/.cache)
RUN useradd --no-create-home --home-dir /work --uid 10001 relight \
 && install -d -o relight -g relight /work \
 && relight --version && relight info \
 && test ! -e /root/.cache
WORKDIR /work
# No USER: the entrypoint starts as root only to become the owner of the output folder (or of
# the inputs when Docker created out/ as root), then execs relight (docker/entrypoint.py).
# With docker run --user it runs as that user from the start.
ENTRYPOINT ["/usr/bin/tini", "--", "/opt/venv/bin/python", "-I", "/usr/local/lib/relight/entrypoint.py"]
CMD ["--help"]
