# relightcli runtime image: ONNX Runtime + Embree on the CPU, no torch, no training code.
#   docker build -t relightcli .
#   docker run --rm -v "$PWD/in:/in" -v "$PWD/out:/out" relightcli /in --hdr /in/sky.hdr -o /out

FROM python:3.11-slim-bookworm AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md requirements.lock ./
COPY relightcli ./relightcli
# The models go into the wheel as package data (relightcli/models in site-packages)
COPY models ./models
RUN python -m venv /opt/venv \
 && /opt/venv/bin/pip install --no-compile -c requirements.lock . \
 && /opt/venv/bin/python -c "import importlib.util as u, sys; sys.exit(u.find_spec('torch') is not None)"

FROM python:3.11-slim-bookworm AS runtime
# No Debian packages beyond the base image: every wheel we install loads only libc, libstdc++,
# libgcc and zlib from the system (tests/test_runtime_env.py checks this with ldd + dpkg).
COPY --from=build /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1
RUN useradd --create-home --uid 10001 relight \
 && relight --version && relight info
USER relight
WORKDIR /work
ENTRYPOINT ["relight"]
CMD ["--help"]
