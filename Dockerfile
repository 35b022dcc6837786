# relightcli runtime image: ONNX Runtime + Embree on the CPU, no torch, no training code.
#   docker build -t relightcli .
#   docker run --rm -v "$PWD/in:/in" -v "$PWD/out:/out" relightcli /in --hdr /in/sky.hdr -o /out

FROM python:3.11-slim-bookworm AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md requirements.lock ./
COPY relightcli ./relightcli
RUN python -m venv /opt/venv \
 && /opt/venv/bin/pip install --no-compile -c requirements.lock . \
 && /opt/venv/bin/python -c "import importlib.util as u, sys; sys.exit(u.find_spec('torch') is not None)"

FROM python:3.11-slim-bookworm AS runtime
# Shared libraries the wheels load at run time (tests/test_runtime_env.py derives this list with
# ldd + dpkg and checks it): pymeshlab fails to import without libGL.so.1, silently loses its I/O
# plugins without libOpenGL.so.0, and links libX11/libxcb; its font plugins need fontconfig.
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
      libgl1 libglx0 libglvnd0 libopengl0 \
      libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 \
      libfontconfig1 libfreetype6 libpng16-16 libbrotli1 \
      libgmp10 libp11-kit0 libffi8 libexpat1 \
 && rm -rf /var/lib/apt/lists/*
COPY --from=build /opt/venv /opt/venv
COPY models /opt/relightcli/models
ENV PATH=/opt/venv/bin:$PATH \
    RELIGHT_MODELS_DIR=/opt/relightcli/models \
    PYTHONDONTWRITEBYTECODE=1
RUN useradd --create-home --uid 10001 relight \
 && relight --version && relight info
USER relight
WORKDIR /work
ENTRYPOINT ["relight"]
CMD ["--help"]
